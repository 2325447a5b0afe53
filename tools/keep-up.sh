#!/usr/bin/env bash
# Issue 33's figures: does the virtual board keep up with its real clients? Prints a
# markdown table on stdout (tools/figures.sh puts it in docs/measurements.md).
#
#   bash tools/keep-up.sh          # about 2 minutes on 2 cores, after the builds
#   bash tools/keep-up.sh --slow   # also the 200-seed first-boot cuts and the ten-seed
#                                  # sweep (tens of minutes)
#
# * `update` typed -> the first YMODEM 'C', wall time: `vboard serve --pty --plc`, a PIN,
#   maintenance mode, `update`, timed by a client on the pty (the time a sender like
#   lrzsz's `sb` waits; it gives up after about 30 s).
# * realtime_factor, the mean and the slowest 100 ms window, of named scenes
#   (`vboard scene NAME --json`).
# * with --slow: the wall time of the 200-seed first-boot power cuts (an ignored test)
#   and of `vboard sweep --flood` (ten seeds, CPI 1-3 and the cache model).
set -euo pipefail
cd "$(dirname "$0")/.."
slow=0
[ "${1:-}" = "--slow" ] && slow=1
vb=./vboard/target/release/vboard
(cd vboard && cargo build -q --release)

field() { python3 -c 'import json,sys; v=json.load(sys.stdin).get(sys.argv[1]); print("null" if v is None else round(v, 2) if isinstance(v, float) else v)' "$1"; }
wall() { local t0 t1; t0=$(date +%s.%N); "$@" >/dev/null 2>&1; t1=$(date +%s.%N); python3 -c "print(f'{$t1-$t0:.0f}')"; }

# The first 'C' after `update` on the live board.
first_c=$(python3 - "$vb" <<'EOF'
import os, select, subprocess, sys, time
vb = sys.argv[1]
p = subprocess.Popen([vb, "serve", "--pty", "--plc", "--for", "300"],
                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
path = p.stdout.readline().decode().strip()
fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
subprocess.run(["stty", "-F", path, "raw", "-echo"], check=True)
def until(want, t):
    got, end = b"", time.time() + t
    while time.time() < end:
        r, _, _ = select.select([fd], [], [], 0.2)
        if r:
            got += os.read(fd, 4096)
            if want in got:
                return got
    raise SystemExit(f"no {want!r} in {got[-200:]!r}")
for cmd, want in [(b"pin set 2468", b"ok: PIN set"), (b"maint 2468", b"ok: maintenance")]:
    for _ in range(30):
        os.write(fd, cmd + b"\r\n")
        try:
            until(want, 5)
            break
        except SystemExit:
            pass
    else:
        raise SystemExit(f"no {want!r}")
time.sleep(0.5)
t0 = time.time()
os.write(fd, b"update\r\n")
# The 'C' may come in the same read as the line before it: what followed the line counts
# (it was dropped, and the figure was the receiver's next 'C', 3 s later: 3.0 s).
got = until(b"of silence cancels\r\n", 30).split(b"of silence cancels\r\n", 1)[1]
while b"C" not in got:
    r, _, _ = select.select([fd], [], [], 60)
    if not r:
        raise SystemExit("no 'C'")
    got += os.read(fd, 1)
print(f"{time.time() - t0:.2f}")
p.kill()
EOF
)

echo "| figure | command | measured |"
echo "|---|---|---|"
echo "| \`update\` typed → first YMODEM 'C', wall | \`vboard serve --pty --plc\`, \`pin set\`, \`maint\`, \`update\` (tools/keep-up.sh) | $first_c s |"
for args in "update" "sector-move" "overload --flood" "nominal"; do
    # shellcheck disable=SC2086
    j=$($vb scene $args --json 2>/dev/null)
    echo "| \`realtime_factor\` mean / slowest 100 ms, \`$args\` | \`vboard scene $args --json\` | $(field realtime_factor <<<"$j") / $(field realtime_factor_min <<<"$j") ($(field sim_time_s <<<"$j") s of machine time, $(field skipped_instructions <<<"$j") instructions in polling loops skipped) |"
done
if [ "$slow" = 1 ]; then
    t=$(wall sh -c 'cd vboard && cargo test -q --release --test update -- --ignored --exact a_power_cut_at_200_instants_of_the_first_boot_boots_a_whole_image')
    echo "| the 200-seed first-boot power cuts | \`cd vboard && cargo test --release --test update -- --ignored --exact a_power_cut_at_200_instants_of_the_first_boot_boots_a_whole_image\` | $t s |"
    t=$(wall $vb sweep --flood)
    echo "| the ten-seed timing sweep, CPI 1–3 and the cache model, flooded | \`vboard sweep --flood\` | $t s |"
fi
