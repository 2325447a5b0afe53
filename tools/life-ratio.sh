#!/usr/bin/env bash
# Issue 20: the CPU time of `hil-sim life --cycles 45270` against 353c5c0's (the commit
# before the board work), as a ratio measured in one run on one machine. Both are built
# from source (release, each in its own git worktree and target directory), then run
# alternately, old then new, a few pairs; the ratio is the median of the pairs' ratios
# of user + system CPU time. The new run's JSON (wall_time_s aside) is also compared with
# the one recorded before the speed-up (tools/life-45270.json), so a faster run is the
# same run.
#
#   bash tools/life-ratio.sh                  # 45 270 cycles, 3 pairs: ~2 min after the builds
#   bash tools/life-ratio.sh --cycles 300     # a smoke run (CI): the ratio is noisy there
#   bash tools/life-ratio.sh --new REV        # measure another commit than HEAD
#   bash tools/life-ratio.sh --pairs 5
#   bash tools/life-ratio.sh --floor          # and the floor: see below
#
# The builds (under a minute each on 2 cores) are kept in target/life-ratio/<commit>/
# (or $LIFE_RATIO_CACHE/<commit>/) and reused; --rebuild builds again. Only committed
# code is measured: commit first. It prints each pair, the median CPU time of each
# commit, and last `ratio X.XX (target <= 0.85)`; it exits 1 if the JSON differs.
#
# --floor also builds the new commit with tools/life-floor.patch applied: its `life`
# runs once with the simulated HX711 and records every code read, then again replaying
# them (a conversion costs one load; the part's data-ready timing is kept), and reports
# the CPU time of the replay alone. That is the run with a load-cell model that costs
# nothing: no work on the simulator's HX711 can take the ratio below it. Its JSON must
# be the new commit's. It also prints how the ticks divide between the sequencer's
# states. The replay holds every code in memory (4 B a sample: 0.85 GB at 45 270
# cycles).
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)

old_rev=353c5c0
new_rev=HEAD
cycles=45270
pairs=3
rebuild=0
floor=0
while [ $# -gt 0 ]; do
    case $1 in
        --cycles) cycles=$2; shift 2 ;;
        --pairs) pairs=$2; shift 2 ;;
        --old) old_rev=$2; shift 2 ;;
        --new) new_rev=$2; shift 2 ;;
        --rebuild) rebuild=1; shift ;;
        --floor) floor=1; shift ;;
        -h | --help) sed -n '2,28p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
        *) echo "life-ratio.sh: unknown argument $1 (--help)" >&2; exit 2 ;;
    esac
done
case $cycles in '' | *[!0-9]*) echo "life-ratio.sh: --cycles takes a number" >&2; exit 2 ;; esac
case $pairs in '' | *[!0-9]* | 0) echo "life-ratio.sh: --pairs takes a number >= 1" >&2; exit 2 ;; esac

cache=${LIFE_RATIO_CACHE:-$repo/target/life-ratio}
tmp=$(mktemp -d)
worktrees=()
cleanup() {
    for w in "${worktrees[@]}"; do git -C "$repo" worktree remove --force "$w" >/dev/null 2>&1 || true; done
    rm -rf "$tmp"
}
trap cleanup EXIT

# Build REV's hil-sim (release) in its own worktree; the binary's path into variable $2
# (not printed: a command substitution's subshell would not record the worktree for
# the clean-up). With a third argument, a patch: applied first, built apart.
build() {
    local sha dir bin patch=${3:-}
    sha=$(git -C "$repo" rev-parse --verify "$1^{commit}")
    dir=$cache/$sha${patch:+-$(basename "$patch" .patch)}
    bin=$dir/release/hil-sim
    if [ "$rebuild" = 1 ] || [ ! -x "$bin" ]; then
        local wt=$tmp/${sha:0:12}${patch:+-floor}
        git -C "$repo" worktree add --detach "$wt" "$sha" >/dev/null 2>&1
        worktrees+=("$wt")
        if [ -n "$patch" ] && ! git -C "$wt" apply "$patch"; then
            echo "life-ratio.sh: $patch does not apply to ${sha:0:12}'s hil-sim (written against 048ccd9)" >&2
            exit 1
        fi
        echo "building ${sha:0:12}'s hil-sim (release) in $wt, target $dir" >&2
        (cd "$wt" && CARGO_TARGET_DIR=$dir cargo build -q --release -p hil-sim >&2)
    fi
    printf -v "$2" '%s' "$bin"
}
build "$old_rev" old_bin
build "$new_rev" new_bin
floor_bin=""
[ "$floor" = 1 ] && build "$new_rev" floor_bin "$repo/tools/life-floor.patch"
old_sha=$(git rev-parse --short "$old_rev^{commit}")
new_sha=$(git rev-parse --short "$new_rev^{commit}")

reference=""
[ "$cycles" = 45270 ] && reference=tools/life-45270.json

python3 - "$old_bin" "$new_bin" "$old_sha" "$new_sha" "$cycles" "$pairs" "$reference" "$floor_bin" <<'EOF'
import json, os, re, statistics, subprocess, sys

old_bin, new_bin, old_sha, new_sha, cycles, pairs, reference, floor_bin = sys.argv[1:]
pairs = int(pairs)
args = ["life", "--cycles", cycles, "--json"]

def run(binary, floor=False):
    """CPU seconds (user + system) of one run, and its JSON without wall_time_s. The
    floor's: the CPU seconds of its replay, as it reports them, and its JSON."""
    if floor:
        p = subprocess.run([binary, *args], capture_output=True, env=dict(os.environ, LIFE_FLOOR="1"))
        out, err, status = p.stdout, p.stderr, p.returncode
    else:
        p = subprocess.Popen([binary, *args], stdout=subprocess.PIPE)
        out = p.stdout.read()
        _, status, ru = os.wait4(p.pid, 0)
    if status != 0:
        sys.exit(f"{binary} {' '.join(args)}: exit status {status}")
    json.loads(out)  # one JSON object
    # The text as printed, wall_time_s aside: "identical" means byte for byte.
    text = re.sub(rb',"wall_time_s":[^,}]*', b"", out).decode().strip()
    if not floor:
        return ru.ru_utime + ru.ru_stime, text
    err = err.decode()
    m = re.search(r"life-floor: replay cpu_s ([0-9.]+)", err)
    if not m:
        sys.exit(f"the floor's run reported no replay time:\n{err}")
    for line in err.splitlines():
        if "by state" in line and line not in states:
            states.append(line)
    return float(m.group(1)), text

print(f"hil-sim {' '.join(args)}: CPU s (user + sys), {old_sha} then {new_sha}, {pairs} pairs")
ratios, reports, olds, news, floors, floor_ratios, states = [], [], [], [], [], [], []
status = 0
for i in range(pairs):
    t_old, _ = run(old_bin)
    t_new, rep = run(new_bin)
    reports.append(rep)
    ratios.append(t_new / t_old)
    olds.append(t_old)
    news.append(t_new)
    line = f"pair {i + 1}: {old_sha} {t_old:.2f} s, {new_sha} {t_new:.2f} s, ratio {t_new / t_old:.3f}"
    if floor_bin:
        t_floor, floor_rep = run(floor_bin, floor=True)
        if floor_rep != rep:
            print(f"FAIL: the floor's replay computed another run:\n  got  {floor_rep}\n  want {rep}")
            status = 1
        floors.append(t_floor)
        floor_ratios.append(t_floor / t_old)
        line += f"; floor {t_floor:.2f} s, ratio {t_floor / t_old:.3f}"
    print(line, flush=True)

if any(r != reports[0] for r in reports):
    print(f"FAIL: {new_sha}'s runs disagree with each other")
    status = 1
if reference:
    with open(reference) as f:
        want = f.read().strip()
    if reports[0] == want:
        print(f"{new_sha}'s JSON (wall_time_s aside) is {reference}'s")
    else:
        print(f"FAIL: {new_sha}'s JSON differs from {reference}:\n  got  {reports[0]}\n  want {want}")
        status = 1
print(f"median CPU: {old_sha} {statistics.median(olds):.2f} s, {new_sha} {statistics.median(news):.2f} s")
for s in states:
    print(s.removeprefix("life-floor: ").replace("ticks, by state", "ticks of the run, by the sequencer's state"))
if floor_bin:
    print(f"floor (the HX711's codes replayed, CPU of the replay): median {statistics.median(floors):.2f} s, "
          f"ratio {statistics.median(floor_ratios):.2f}")
print(f"ratio {statistics.median(ratios):.2f} (target <= 0.85)")
sys.exit(status)
EOF
