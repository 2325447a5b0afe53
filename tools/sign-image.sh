#!/usr/bin/env bash
# Sign an application image for a field update (issue 21, docs/update.md): the update
# file the console's `update` command receives by YMODEM-1K.
#
#   bash tools/sign-image.sh [ELF [KEY [OUT]]]
#     ELF  the application (default: the release image, linked at 0x08008000)
#     KEY  the integrator's ed25519 key, PEM (default: boot/keys/test-signing-key.pem,
#          the TEST key: an image it signs proves nothing)
#     OUT  the update file (default: target/update.dcs)
#
# The file: the image's bytes (llvm-objcopy -O binary: from 0x08008000, padded with
# 0xFF to whole words), then a 72-byte trailer: the ed25519 signature (64 B) of the
# SHA-512 of those bytes (embassy-boot's verify_and_mark_updated checks exactly that),
# the length (u32 LE), the magic "DCS1". Needs llvm-objcopy (Debian: llvm) and openssl.
set -euo pipefail
cd "$(dirname "$0")/.."
elf=${1:-target/thumbv7em-none-eabihf/release/docking-controller}
key=${2:-boot/keys/test-signing-key.pem}
out=${3:-target/update.dcs}
objcopy=$(command -v llvm-objcopy || command -v llvm-objcopy-14 || true)
if [ -z "$objcopy" ]; then
    echo "sign-image: llvm-objcopy not found (apt-get install llvm)" >&2
    exit 1
fi
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$objcopy" -O binary "$elf" "$tmp/app.bin"
len=$(stat -c %s "$tmp/app.bin")
pad=$(( (4 - len % 4) % 4 ))
if [ "$pad" -gt 0 ]; then
    head -c "$pad" /dev/zero | tr '\0' '\377' >> "$tmp/app.bin"
    len=$((len + pad))
fi
# The vector table must point into ACTIVE: an image linked at 0x08000000 is refused here.
reset=$(od -An -tx4 -j4 -N4 "$tmp/app.bin" | tr -d ' ')
case "$reset" in
    0800[89a-f]*|080[1-3]*) ;;
    *) echo "sign-image: $elf's reset vector is 0x$reset: not linked behind the bootloader (0x08008000)" >&2; exit 1 ;;
esac
openssl dgst -sha512 -binary "$tmp/app.bin" > "$tmp/app.sha512"
openssl pkeyutl -sign -inkey "$key" -rawin -in "$tmp/app.sha512" -out "$tmp/app.sig"
openssl pkey -in "$key" -pubout -out "$tmp/pub.pem"
openssl pkeyutl -verify -pubin -inkey "$tmp/pub.pem" -rawin -in "$tmp/app.sha512" -sigfile "$tmp/app.sig" >/dev/null
mkdir -p "$(dirname "$out")"
{
    cat "$tmp/app.bin" "$tmp/app.sig"
    printf "$(printf '\\x%02x\\x%02x\\x%02x\\x%02x' $((len & 255)) $(((len >> 8) & 255)) $(((len >> 16) & 255)) $(((len >> 24) & 255)))"
    printf 'DCS1'
} > "$out"
pub=$(openssl pkey -in "$key" -pubout -outform DER | tail -c 32 | od -An -tx1 | tr -d ' \n')
echo "$out: $len B image + 72 B trailer, signed by ed25519 key $pub"
