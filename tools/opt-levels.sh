#!/usr/bin/env bash
# The release profile's opt-level, chosen by measurement: for each level, build the
# image (own target dir), report its flash size, then run the virtual board's
# `overload` scene on it for the stop latency at the pins and the control step's cost.
# Usage: tools/opt-levels.sh [LEVELS...]   (default: z s 2 3; about 10 minutes on 2 cores)
set -euo pipefail
cd "$(dirname "$0")/.."
levels=("$@")
[ $# -eq 0 ] && levels=(z s 2 3)
T=thumbv7em-none-eabihf
# The virtual board boots every image through the bootloader (issue 21, docs/update.md).
(cd boot && cargo build -q --release)
(cd vboard && cargo build -q --release)
printf '%-5s %10s %18s %22s %16s\n' level flash_B stop_latency_us control_step_insns exti0_insns
for l in "${levels[@]}"; do
    dir="target/opt-$l"
    CARGO_PROFILE_RELEASE_OPT_LEVEL="$l" cargo build -q --release --target "$T" --target-dir "$dir"
    elf="$dir/$T/release/docking-controller"
    flash=$(size -A "$elf" | awk '$1 == ".vector_table" || $1 == ".text.hot" || $1 == ".text" || $1 == ".rodata" || $1 == ".data" { t += $2 } END { print t }')
    json=$(vboard/target/release/vboard scene overload --firmware "$elf" --json)
    python3 - "$l" "$flash" "$json" <<'PY'
import json, sys
l, flash, j = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
exti = next((t["instructions"] / max(t["entries"], 1) for t in j["tasks"] if t["name"] == "EXTI0"), float("nan"))
print(f"{l:<5} {flash:>10} {j['stop_latency_pins_us']:>18.1f} {j['instructions_per_control_step']:>22.0f} {exti:>16.0f}")
PY
done
