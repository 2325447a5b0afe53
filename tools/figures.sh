#!/usr/bin/env bash
# The measured figures on one page: builds the image and the simulators, runs the
# benchmarks and the virtual board's scenes, and writes docs/measurements.md stamped
# with the commit it measured (issue 19: a figure in the docs comes from a command that
# regenerates it).
#
#   bash tools/figures.sh            # about 7 minutes on 2 cores, after the builds
#   bash tools/figures.sh --sweep    # also the full timing sweep (80 runs) and the
#                                    # 200-seed first-boot cuts (tools/keep-up.sh --slow)
#
# The virtual board's table is measured twice: on this tree's image and on the image of
# $FIGURES_BEFORE (default b20ffb8, the tree before issue 20), built from source in a
# git worktree (kept in target/figures-before/<commit>/) and run on this tree's virtual
# board, so that the two columns differ only in the image.
#
# Run it from a clean tree: the page says which commit it measured, and "(dirty)" when
# the tree had changes.
set -euo pipefail
cd "$(dirname "$0")/.."
out=docs/measurements.md
sweep=0
[ "${1:-}" = "--sweep" ] && sweep=1

commit=$(git rev-parse --short HEAD)
git diff --quiet HEAD -- || commit="$commit (dirty)"
TARGET=thumbv7em-none-eabihf
elf=target/$TARGET/release/docking-controller

cargo build -q --release --target "$TARGET"
cargo build -q --release -p hil-sim
# The virtual board boots every image through the bootloader (issue 21, docs/update.md).
(cd boot && cargo build -q --release)
(cd vboard && cargo build -q --release)
# The image before issue 20, for the before/after table.
before_rev=${FIGURES_BEFORE:-b20ffb8}
before_sha=$(git rev-parse --verify "$before_rev^{commit}")
before_elf=$PWD/target/figures-before/$before_sha/$TARGET/release/docking-controller
if [ ! -f "$before_elf" ]; then
    wt=$(mktemp -d)/before
    git worktree add --detach "$wt" "$before_sha" >/dev/null 2>&1
    (cd "$wt" && CARGO_TARGET_DIR=$PWD/../target cargo build -q --release --target "$TARGET" &&
        mkdir -p "$(dirname "$before_elf")" && cp "$PWD/../target/$TARGET/release/docking-controller" "$before_elf")
    git worktree remove --force "$wt"
    rm -rf "$(dirname "$wt")"
fi
hil=./target/release/hil-sim
vb=./vboard/target/release/vboard

# One JSON field of a one-line JSON object.
field() { python3 -c 'import json,sys; v=json.load(sys.stdin).get(sys.argv[1]); print("null" if v is None else v)' "$1"; }
# Wall seconds of a command (its output discarded).
wall() { local t0 t1; t0=$(date +%s.%N); "$@" >/dev/null; t1=$(date +%s.%N); python3 -c "print(f'{$t1-$t0:.1f}')"; }

# Flash and static RAM of an image, as `cargo xtask size` counts them.
sizes() {
    size -A "$1" | awk '
    $1 == ".vector_table" || $1 == ".image_header" || $1 == ".text.hot" || $1 == ".text" || $1 == ".rodata" { t += $2 }
    $1 == ".data" { d += $2 }
    $1 == ".bss" || $1 == ".uninit" { b += $2 }
    END { print t + 0, d + 0, b + 0 }'
}
read -r text data bss < <(sizes "$elf")
# The image without its updater (the updater's cost): `cargo xtask size` builds it (in
# the same target directory, from cargo's cache) and copies it to target/lean; its
# verdict on the size policy is not this page's business, its images are.
size_out=$(cargo xtask size 2>/dev/null || true)
read -r ltext ldata lbss < <(sizes "target/lean/$TARGET/release/docking-controller")
update_file_line=$(grep '^update file:' <<<"$size_out" || true)
# The bootloader's swap and revert (issue 31), and a PLC polling through an odometer
# sector move at the maximum erase time.
swap_table=$($vb swap-time 2>/dev/null || echo "vboard swap-time failed")
# The update's transfer against the line's limit (issue 35): the scene's check of it.
pace() { $vb scene update --flash-timing "$1" --json 2>/dev/null |
    python3 -c 'import json,sys; print(next((c["detail"] for c in json.load(sys.stdin)["checks"] if "pace" in c["name"]), "no pace check"))' ||
    echo "vboard scene update failed"; }
pace_typical=$(pace typical)
pace_max=$(pace max)
sector_json=$($vb scene sector-move --json 2>/dev/null || echo '{}')

bench=$($hil bench --cycles 1000)
ns_step=$(sed -E 's/.* ([0-9]+) ns per control step.*/\1/' <<<"$bench")
life_s=$(wall $hil life --cycles 45270)
life_json=$($hil life --cycles 45270 --json)
life_cycles=$(field life_cycles <<<"$life_json")
# Issue 20: life's CPU time against 353c5c0's, both built from source (3 pairs, ~2 min).
ratio_out=$(bash tools/life-ratio.sh 2>/dev/null)
ratio=$(sed -n 's/^ratio \([0-9.]*\).*/\1/p' <<<"$ratio_out")
ratio_cpu=$(sed -n 's/^median CPU: //p' <<<"$ratio_out")

scene_row() { # model args...: one table row from `vboard scene overload --flood` and `scene estop`
    local model=$1; shift
    local o e
    o=$($vb scene overload --flood --json "$@")
    e=$($vb scene estop --json "$@")
    printf '| %s | %s µs | %s ms | %s µs | %s | %s µs | %s µs |\n' "$model" \
        "$(field stop_latency_pins_us <<<"$o")" "$(field control_period_max_ms <<<"$o")" \
        "$(field control_entry_latency_max_us <<<"$o")" "$(field instructions_per_control_step <<<"$o")" \
        "$(field masked_max_us <<<"$o")" "$(field estop_off_max_us <<<"$e")"
}

{
    echo "# Measured figures"
    echo
    echo "Written by \`bash tools/figures.sh\` on commit $commit, $(date -u +%Y-%m-%d), on a"
    echo "$(nproc)-core $(uname -m) machine. Every figure below comes from the command beside it;"
    echo "run the script again after a change and commit the page with it."
    echo
    echo "## The image (\`cargo build --release --target $TARGET\`, \`size -A\`)"
    echo
    echo "| image | flash (text + rodata + vectors + header + data) | static RAM (data + bss + uninit) |"
    echo "|---|---|---|"
    echo "| with its updater (the default) | $((text + data)) B | $((data + bss)) B (at most 32 768 B) |"
    echo "| without (\`--no-default-features\`): the updater costs $((text + data - ltext - ldata)) B | $((ltext + ldata)) B | $((ldata + lbss)) B |"
    echo
    echo "The size policy's figure (\`cargo xtask size\`; docs/update.md, \"Size\"): $update_file_line"
    echo
    echo "The 10 biggest functions (\`python3 tools/size-report.py -n 10 --no-groups $elf\`):"
    echo
    echo '```'
    python3 tools/size-report.py -n 10 --no-groups "$elf"
    echo '```'
    echo
    echo "## The host simulator"
    echo
    echo "| command | figure |"
    echo "|---|---|"
    echo "| \`hil-sim bench --cycles 1000\` | $ns_step ns per control step (controller + simulated HAL) |"
    echo "| \`hil-sim life --cycles 45270\` | $life_s s wall; the cone's limit at cycle $life_cycles |"
    echo "| \`bash tools/life-ratio.sh\` | CPU time of that run against 353c5c0's, median of 3 pairs: **$ratio** (target ≤ 0.85; $ratio_cpu) |"
    echo
    echo "## The virtual board (the release image; \`cd vboard\`)"
    echo
    echo "\`vboard scene overload --flood --json\` (console and Modbus flooded) and"
    echo "\`vboard scene estop --json\`, seed 1, at each timing model:"
    echo
    echo "| model | overload stop, DOUT → EN high | control period, max | control entry latency while moving | instructions per control step | longest all-masked window | E-STOP edge → EN high |"
    echo "|---|---|---|---|---|---|---|"
    scene_row "CPI 1"
    scene_row "CPI 3" --cpi 3
    scene_row "ART cache, CPI 1" --timing art
    echo
    echo "The same on the image of ${before_sha:0:7} (before issue 20), built from source and run"
    echo "on this virtual board (\`--firmware\`):"
    echo
    echo "| model | overload stop, DOUT → EN high | control period, max | control entry latency while moving | instructions per control step | longest all-masked window | E-STOP edge → EN high |"
    echo "|---|---|---|---|---|---|---|"
    scene_row "CPI 1" --firmware "$before_elf"
    scene_row "CPI 3" --cpi 3 --firmware "$before_elf"
    scene_row "ART cache, CPI 1" --timing art --firmware "$before_elf"
    echo
    echo "The bootloader's swap and revert (\`vboard swap-time\`; docs/update.md, \"Swap time\"):"
    echo
    echo '```'
    echo "$swap_table"
    echo '```'
    echo
    echo "The update's transfer over the console, YMODEM-1K at 115 200 Bd 8N1 (11 520 B/s), the"
    echo "release image's update file sent by the project's sender (\`vboard scene update --json\`,"
    echo "its pace check; docs/update.md, \"dockctl\"):"
    echo
    echo "| flash times | the transfer |"
    echo "|---|---|"
    echo "| typical | $pace_typical |"
    echo "| datasheet's maximum | $pace_max |"
    echo
    echo "A PLC's master polling input registers every 100 ms through an odometer sector move"
    echo "at the maximum erase time (\`vboard scene sector-move --json\`; docs/modbus.md): $(field modbus_polls <<<"$sector_json") requests,"
    echo "$(field modbus_poll_busy <<<"$sector_json") answered busy (exception 06) during the erase, $(field modbus_poll_timeouts <<<"$sector_json") unanswered, the longest"
    echo "wait for a reply $(field modbus_reply_max_ms <<<"$sector_json") ms."
    echo
    echo "## Keeping up with real clients (issue 33: \`bash tools/keep-up.sh\`; \`--slow\` with \`--sweep\`)"
    echo
    if [ "$sweep" = 1 ]; then bash tools/keep-up.sh --slow; else bash tools/keep-up.sh; fi
    echo
    echo "## The docking signature (issue 34; docs/physics.md §10)"
    echo
    echo "Its cost on the image (\`vboard signature-cost\`, at 80 and 10 SPS):"
    echo
    echo '```'
    $vb signature-cost 2>&1
    $vb signature-cost --rate 10 2>&1
    echo '```'
    echo
    echo "Can it see wear? (\`hil-sim signature-study\`):"
    echo
    echo '```'
    $hil signature-study 2>&1
    echo '```'
    if [ "$sweep" = 1 ]; then
        echo
        echo "The worst case over seeds 1–10 and every model (\`vboard sweep --flood\`):"
        echo
        echo '```'
        $vb sweep --flood 2>/dev/null
        echo '```'
    fi
} >"$out"
echo "wrote $out"
