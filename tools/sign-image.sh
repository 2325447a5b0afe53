#!/usr/bin/env bash
# Sign an application image for a field update (issue 21, docs/update.md): the update
# file the console's `update` command receives by YMODEM-1K.
#
#   bash tools/sign-image.sh [--version X.Y.Z[+B]] [ELF [KEY [OUT]]]
#     --version  stamp this version into the image header before signing (as MCUboot's
#                `imgtool sign --version` does): the signature covers it, and one build
#                gives images of several versions (default: the build's own, Cargo.toml)
#     ELF  the application (default: the release image, linked behind the bootloader at
#          ACTIVE's first address: 0x08020000 in layout C)
#     KEY  the integrator's ed25519 key, PEM (default: boot/keys/test-signing-key.pem,
#          the TEST key: an image it signs proves nothing)
#     OUT  the update file (default: target/update.dcs)
#
# The file: the image's bytes (llvm-objcopy -O binary: from ACTIVE's first address,
# padded with 0xFF to whole words), then a 72-byte trailer: the ed25519 signature (64 B) of the
# SHA-512 of those bytes (embassy-boot's verify_and_mark_updated checks exactly that),
# the length (u32 LE), the magic "DCS1". The image header (32 bytes at 0x200, after the
# vector table: update-layout/src/header.rs) holds the version: --version writes it
# (major u8, minor u8, patch u16 LE, build u32 LE at 0x204) and sets the header's flag
# "stamped" (bit 0 of the u32 at 0x20C; bits 8-15, the byte at 0x20D, name the layout the
# image is linked for). The layout is not copied here: build.rs gives it to the ELF as
# the symbols __layout_id, __active_start and __active_end (from update-layout), and the
# image is checked against them. Needs llvm-objcopy and llvm-nm (Debian: llvm) and openssl.
set -euo pipefail
cd "$(dirname "$0")/.."
version=""
if [ "${1:-}" = "--version" ]; then
    version=${2:?"--version needs X.Y.Z[+B]"}
    shift 2
fi
elf=${1:-target/thumbv7em-none-eabihf/release/docking-controller}
key=${2:-boot/keys/test-signing-key.pem}
out=${3:-target/update.dcs}
objcopy=$(command -v llvm-objcopy || command -v llvm-objcopy-14 || true)
nm=$(command -v llvm-nm || command -v llvm-nm-14 || true)
if [ -z "$objcopy" ] || [ -z "$nm" ]; then
    echo "sign-image: llvm-objcopy or llvm-nm not found (apt-get install llvm)" >&2
    exit 1
fi
if [ ! -f "$elf" ]; then
    echo "sign-image: no such ELF: $elf (build it: cargo build --release --target thumbv7em-none-eabihf)" >&2
    exit 1
fi
# The layout the ELF was linked for (build.rs's symbols, from update-layout).
sym() { "$nm" "$elf" 2>/dev/null | awk -v s="$1" '$3 == s { print $1 }'; }
layout_id=$(sym __layout_id) active_start=$(sym __active_start) active_end=$(sym __active_end)
if [ -z "$layout_id" ] || [ -z "$active_start" ] || [ -z "$active_end" ]; then
    echo "sign-image: $elf names no layout (no __layout_id/__active_start/__active_end): not linked behind the bootloader by this project's build.rs" >&2
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
reset=$((16#$(od -An -tx4 -j4 -N4 "$tmp/app.bin" | tr -d ' ')))
if [ "$reset" -le $((16#$active_start)) ] || [ "$reset" -ge $((16#$active_end)) ]; then
    printf 'sign-image: %s: reset vector 0x%08x outside ACTIVE (0x%s-0x%s): not linked behind the bootloader\n' \
        "$elf" "$reset" "$active_start" "$active_end" >&2
    exit 1
fi
# The image header: its magic at 0x200, then the version to stamp.
header_magic=$(od -An -c -j512 -N4 "$tmp/app.bin" | tr -d ' ')
if [ "$header_magic" != "DCIH" ]; then
    echo "sign-image: $elf has no image header at 0x200 (update-layout/src/header.rs)" >&2
    exit 1
fi
# The header names the layout the ELF is linked for (the updater refuses another's).
header_layout=$(od -An -tu1 -j525 -N1 "$tmp/app.bin" | tr -d ' ')
if [ "$header_layout" != "$((16#$layout_id))" ]; then
    echo "sign-image: $elf's header names layout $header_layout, its link layout $((16#$layout_id))" >&2
    exit 1
fi
le() { # VALUE BYTES: VALUE as BYTES bytes, little-endian, as printf escapes
    local v=$1 n=$2 i s=""
    for ((i = 0; i < n; i++)); do s="$s$(printf '\\x%02x' $(((v >> (8 * i)) & 255)))"; done
    printf '%s' "$s"
}
if [ -n "$version" ]; then
    if ! [[ "$version" =~ ^([0-9]+)\.([0-9]+)\.([0-9]+)(\+([0-9]+))?$ ]]; then
        echo "sign-image: version '$version' is not X.Y.Z or X.Y.Z+B" >&2
        exit 1
    fi
    major=${BASH_REMATCH[1]} minor=${BASH_REMATCH[2]} patch=${BASH_REMATCH[3]} build=${BASH_REMATCH[5]:-0}
    if [ "$major" -gt 255 ] || [ "$minor" -gt 255 ] || [ "$patch" -gt 65535 ] || [ "$build" -gt 4294967295 ]; then
        echo "sign-image: version '$version' out of range (255.255.65535+4294967295)" >&2
        exit 1
    fi
    flags=$(od -An -tu4 -j524 -N4 "$tmp/app.bin" | tr -d ' ')
    printf "$(le "$major" 1)$(le "$minor" 1)$(le "$patch" 2)$(le "$build" 4)$(le $((flags | 1)) 4)" |
        dd of="$tmp/app.bin" bs=1 seek=516 conv=notrunc status=none
fi
stamped=$(od -An -tu1 -j516 -N4 "$tmp/app.bin" | awk '{printf "%d.%d.%d", $1, $2, $3 + 256 * $4}')
build_no=$(od -An -tu4 -j520 -N4 "$tmp/app.bin" | tr -d ' ')
[ "$build_no" != 0 ] && stamped="$stamped+$build_no"
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
trusts=$(od -An -tx1 -j528 -N16 "$tmp/app.bin" | tr -d ' \n')
echo "$out: version $stamped, layout $(printf "\\x$(printf %x $((64 + 16#$layout_id)))"), $len B image + 72 B trailer, signed by ed25519 key $pub (the image verifies its own updates with key ${trusts}...)"
