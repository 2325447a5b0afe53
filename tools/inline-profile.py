#!/usr/bin/env python3
"""Instructions per control step of the closed loop, by function *including inlined
code* (callgrind alone credits everything inlined into `Rig::tick` to that one symbol).

    cargo build --release -p hil-sim
    valgrind --tool=callgrind --dump-instr=yes --callgrind-out-file=cg.out \\
        target/release/hil-sim life --cycles 50
    python3 tools/inline-profile.py cg.out target/release/hil-sim 232853

232853 = control steps of `life --cycles 50` (its `# … s simulated` line × 80 SPS).
Each executed instruction of the binary is charged once to every function on its
inline stack (addr2line -i), so a row is that function's inclusive cost; calls that
are not inlined appear as their own rows. Needs valgrind and binutils (addr2line).
"""
import collections
import re
import subprocess
import sys


def costs_by_address(cg_path, binary_name):
    """Self cost (Ir) per instruction address of the object `binary_name`."""
    costs = collections.Counter()
    names = {}  # object id -> path: callgrind names an object once, by ob= or cob=
    obj, last, after_calls = "", 0, False
    for ln in open(cg_path):
        ln = ln.rstrip("\n")
        if ln.startswith(("ob=", "cob=")):
            ident, _, path = ln.split("=", 1)[1].partition(" ")
            if path:
                names[ident] = path
            if ln.startswith("ob="):
                obj = names.get(ident, "")
            continue
        if ln.startswith("fn="):
            after_calls = False
            continue
        if ln.startswith(("cfi=", "cfn=", "cfl=", "fl=", "fi=", "fe=")):
            continue
        if ln.startswith("calls="):
            after_calls = True  # the next line is the call's inclusive cost
            continue
        if not ln:
            continue
        a = ln.split()[0]
        # Positions are absolute (0x…) or relative to the previous one, in decimal.
        if a.startswith("0x"):
            addr = int(a, 16)
        elif a.startswith("+"):
            addr = last + int(a[1:])
        elif a.startswith("-"):
            addr = last - int(a[1:])
        elif a == "*":
            addr = last
        else:
            continue
        last = addr
        if after_calls:
            after_calls = False
            continue
        if obj.endswith("/" + binary_name):
            costs[addr] += int(ln.split()[-1])
    return costs


def inline_stacks(binary, addrs):
    out = subprocess.run(
        ["addr2line", "-e", binary, "-i", "-f", "-C", "-a"] + [hex(a) for a in addrs],
        capture_output=True, text=True, check=True,
    ).stdout.split("\n")
    frames, cur, i = {}, None, 0
    while i < len(out):
        line = out[i]
        if line.startswith("0x"):
            cur = int(line, 16)
            frames[cur] = []
            i += 1
        elif line and i + 1 < len(out):
            frames[cur].append(line)
            i += 2
        else:
            i += 1
    return frames


def main():
    if len(sys.argv) < 4:
        sys.exit(__doc__)
    cg, binary, steps = sys.argv[1], sys.argv[2], float(sys.argv[3])
    rows = int(sys.argv[4]) if len(sys.argv) > 4 else 50
    costs = costs_by_address(cg, binary.rsplit("/", 1)[-1])
    frames = inline_stacks(binary, sorted(costs))
    incl = collections.Counter()
    generics = re.compile(r"<[^<>]*(<[^<>]*>[^<>]*)*>")
    for addr, c in costs.items():
        seen = set()
        for f in frames.get(addr, []):
            k = generics.sub("<>", f)
            if k not in seen:
                seen.add(k)
                incl[k] += c
    print(f"{sum(costs.values()) / steps:8.1f}  (all of {binary}, per step)")
    for k, c in incl.most_common(rows):
        print(f"{c / steps:8.1f}  {k[:140]}")


if __name__ == "__main__":
    main()
