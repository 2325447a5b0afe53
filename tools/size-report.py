#!/usr/bin/env python3
"""Where the firmware's flash goes, by function and by crate/module (issue 20): a
`cargo bloat`-style report read from the ELF with binutils alone (nm, size, addr2line).

    cargo build --release --target thumbv7em-none-eabihf
    python3 tools/size-report.py                      # top 30 functions, then crates and modules
    python3 tools/size-report.py -n 20 --no-groups    # what .ci/run prints
    python3 tools/size-report.py --depth 3            # modules one level deeper
    python3 tools/size-report.py --inlined idle       # what was inlined into `...::idle`
    python3 tools/size-report.py --inlined idle --inlined-depth 2   # two inline levels
    python3 tools/size-report.py --baseline old.elf   # per-function differences to another image
    python3 tools/size-report.py --baseline tools/size-baseline.txt   # ... to a recorded one
    python3 tools/size-report.py --record tools/size-baseline.txt     # record this image's sizes
    python3 tools/size-report.py --inline-sites       # functions inlined at several places

Every symbol that occupies flash is counted: code and read-only data (`t T r R`), the
initial image of `.data` (`d D`, RAM functions included: they are copied from flash),
each address once (aliases such as `__aeabi_*` are folded into their Rust name).
Names are demangled by `nm -C` (legacy and v0 Rust mangling, binutils >= 2.36).
A symbol's crate is that of the type or path it belongs to (`<a::T as b::Tr>::f` is
crate `a`); `.Lanon.*` constants are grouped as `[anonymous constants]`.

`--inlined SYMBOL` breaks one function's bytes down by the functions inlined into it,
from the DWARF line tables (`addr2line -i` on every halfword): `self` is the bytes whose
innermost frame is that function, `incl.` the bytes with it anywhere in the inline stack.
Needs the release profile's `debug = 2` (it does not change the image).

`--record FILE` writes this image's figures (its flash, then every symbol's size, one a
line) to FILE, headed by the commit it was built from: the size policy's baseline
(`cargo xtask size` compares the image with it function by function, docs/board.md,
"Flash and size"). `--baseline` takes such a file as well as an ELF.

`--inline-sites` lists the functions the compiler inlined at two or more places, from
the DWARF inline records (`llvm-dwarfdump`, Debian's `llvm`): the number of copies,
their bytes, and what one copy fewer of each would save at most. A function with many
big copies in code built at `s` (what is generic over the board, and what is inlined
into it) is worth trying `#[inline(never)]` on: issue 20's size pass took 2 372 B that
way (e.g. `Sequencer::move_deadline`, nine copies, -592 B), and measured each (a small
function inlined folds into its callers: out of line it can cost bytes instead).
"""
import argparse
import collections
import os
import re
import subprocess
import sys

DEFAULT_ELF = "target/thumbv7em-none-eabihf/release/docking-controller"
FLASH_TYPES = set("tTrRdDvVwW")
# .image_header: the image header (issue 21); .text.hot: the safety path's handlers,
# aligned to flash cache lines (hot.x).
FLASH_SECTIONS = (".vector_table", ".image_header", ".text.hot", ".text", ".rodata", ".data")


def run(cmd):
    return subprocess.run(cmd, check=True, capture_output=True, text=True).stdout


def section_sizes(elf):
    sizes = {}
    for ln in run(["size", "-A", elf]).splitlines():
        parts = ln.split()
        if len(parts) >= 3 and parts[0].startswith(".") and parts[1].isdigit():
            sizes[parts[0]] = int(parts[1])
    return sizes


def symbols(elf):
    """(address, size, type, demangled name) of every flash-resident symbol, one per address."""
    by_addr = {}
    for ln in run(["nm", "-S", "--size-sort", "-C", elf]).splitlines():
        parts = ln.split(" ", 3)
        if len(parts) != 4 or parts[2] not in FLASH_TYPES:
            continue
        addr, size, kind, name = int(parts[0], 16), int(parts[1], 16), parts[2], parts[3]
        # Thumb functions carry bit 0; an alias at the same address is the same bytes.
        key = addr & ~1 if kind in "tTwW" else addr
        old = by_addr.get(key)
        if old is None or rank(name) > rank(old[3]):
            by_addr[key] = (key, size, kind, name)
    return list(by_addr.values())


def rank(name):
    """Prefer a Rust path over a C alias (`__aeabi_memcpy` vs `compiler_builtins::mem::memcpy`)."""
    return (("::" in name), -name.startswith("__"), len(name))


def split_top(s, sep):
    """Split `s` at `sep` outside <...>, (...) and [...]."""
    out, depth, cur, i = [], 0, [], 0
    while i < len(s):
        c = s[i]
        if c in "<([":
            depth += 1
        elif c in ">)]" and depth > 0:
            depth -= 1
        if depth == 0 and s.startswith(sep, i):
            out.append("".join(cur))
            cur = []
            i += len(sep)
            continue
        cur.append(c)
        i += 1
    out.append("".join(cur))
    return out


def path_of(name):
    """The module path a symbol belongs to, as a list of segments."""
    if name.startswith(".Lanon") or name.startswith(".L"):
        return ["[anonymous constants]"]
    if name.startswith("<"):
        # `<T as Trait>::f` or `<T>::f`: the path of T.
        inner, depth = [], 0
        for c in name[1:]:
            if c == "<":
                depth += 1
            elif c == ">":
                if depth == 0:
                    break
                depth -= 1
            inner.append(c)
        t = split_top("".join(inner), " as ")[0].strip().lstrip("&*").replace("mut ", "")
        if t.startswith("dyn "):
            t = t[4:]
        return path_of(t) if "::" in t else ["[primitive]", t]
    segs = [re.sub(r"<.*", "", s) for s in split_top(name, "::")]
    if len(segs) == 1:
        return ["[no crate]", name]
    return segs


def group_key(name, depth):
    segs = path_of(name)
    if segs[0].startswith("["):
        return segs[0]
    # Drop the item itself (function, type) so that a module is what remains: keep at most
    # `depth` segments, and never the last one unless the path is that short.
    mods = segs[:-1] if len(segs) > 1 else segs
    # Type segments (capitalised) end the module path: `a::b::T::f` is module `a::b`.
    cut = []
    for s in mods:
        if s[:1].isupper() or s.startswith("{"):
            break
        cut.append(s)
    return "::".join((cut or mods[:1])[:depth])


def fmt_bytes(n):
    return f"{n:>8,}".replace(",", " ")


def report(elf, top, depth, groups):
    sizes = section_sizes(elf)
    flash = sum(sizes.get(s, 0) for s in FLASH_SECTIONS)
    syms = symbols(elf)
    counted = sum(s[1] for s in syms)
    print(f"{elf}: flash {flash} B (" + ", ".join(f"{s} {sizes.get(s, 0)}" for s in FLASH_SECTIONS) + ")")
    print(f"{len(syms)} symbols hold {counted} B; {flash - counted} B are padding, tables and unnamed code")
    print(f"\ntop {top} symbols by size:")
    print(f"{'bytes':>8} {'%':>5}  kind  name")
    for addr, size, kind, name in sorted(syms, key=lambda s: -s[1])[:top]:
        print(f"{fmt_bytes(size)} {100 * size / flash:5.1f}  {kind:>4}  {name}")
    if not groups:
        return
    for title, d in (("crate", 1), (f"module (depth {depth})", depth)):
        tot = collections.Counter()
        cnt = collections.Counter()
        for _, size, _, name in syms:
            k = group_key(name, d)
            tot[k] += size
            cnt[k] += 1
        print(f"\nby {title}:")
        print(f"{'bytes':>8} {'%':>5}  {'syms':>4}  name")
        for k, v in tot.most_common():
            print(f"{fmt_bytes(v)} {100 * v / flash:5.1f}  {cnt[k]:>4}  {k}")


def inlined(elf, pattern, top, level):
    syms = [s for s in symbols(elf) if s[2] in "tTwW" and pattern in s[3]]
    if not syms:
        sys.exit(f"no function matches {pattern!r}")
    total = sum(s[1] for s in syms)
    addrs = []
    for addr, size, _, _ in syms:
        addrs.extend(range(addr, addr + size, 2))
    out = subprocess.run(
        ["addr2line", "-a", "-i", "-f", "-C", "-e", elf],
        input="\n".join(hex(a) for a in addrs) + "\n",
        check=True, capture_output=True, text=True,
    ).stdout.splitlines()
    self_b = collections.Counter()
    incl_b = collections.Counter()
    stack = []

    def flush():
        if not stack:
            return
        chain = stack[::-1]  # addr2line -i lists the innermost frame first; outermost first here
        # Bytes whose inline stack is shallower than `level` stay with their innermost frame.
        key = chain[level] if level < len(chain) else f"(own code) {chain[-1]}"
        self_b[key] += 2
        for f in set(chain):
            incl_b[f] += 2

    i = 0
    while i < len(out):
        ln = out[i]
        if ln.startswith("0x"):
            flush()
            stack = []
            i += 1
            continue
        stack.append(re.sub(r"::h[0-9a-f]{16}$", "", ln))
        i += 2  # skip file:line
    flush()
    names = ", ".join(s[3] for s in syms[:3]) + (" ..." if len(syms) > 3 else "")
    print(f"{total} B in {len(syms)} function(s) matching {pattern!r}: {names}")
    print(f"\nby inlined function at inline level {level} (0 = the symbol itself):")
    print(f"{'bytes':>8} {'%':>5}  name")
    for k, v in self_b.most_common(top):
        print(f"{fmt_bytes(v)} {100 * v / total:5.1f}  {k}")
    print(f"\ninclusive (bytes with the function anywhere in the inline stack):")
    for k, v in incl_b.most_common(top):
        print(f"{fmt_bytes(v)} {100 * v / total:5.1f}  {k}")


def inline_sites(elf, top):
    out = run(["llvm-dwarfdump", "--debug-info", elf]).split("\n")
    sites = collections.defaultdict(list)
    i, n = 0, len(out)
    while i < n:
        if "DW_TAG_inlined_subroutine" not in out[i]:
            i += 1
            continue
        name, size, lo = None, 0, 0
        j = i + 1
        while j < n and "DW_TAG" not in out[j]:
            t = out[j]
            m = re.search(r'DW_AT_abstract_origin\s+\(0x[0-9a-f]+ "([^"]+)"', t)
            if m:
                name = m.group(1)
            m = re.search(r"DW_AT_low_pc\s+\((0x[0-9a-f]+)\)", t)
            if m:
                lo = int(m.group(1), 16)
            m = re.search(r"DW_AT_high_pc\s+\((0x[0-9a-f]+)\)", t)
            if m:
                size += int(m.group(1), 16) - lo
            for a, b in re.findall(r"\[(0x[0-9a-f]+), (0x[0-9a-f]+)\)", t):
                size += int(b, 16) - int(a, 16)
            j += 1
        if name:
            sites[name].append(size)
        i = j
    names = [k for k, v in sites.items() if len(v) >= 2]
    dem = subprocess.run(["c++filt"], input="\n".join(names), capture_output=True, text=True).stdout.split("\n")
    rows = []
    for k, d in zip(names, dem):
        v = sites[k]
        rows.append((sum(v) - max(v), len(v), sum(v), re.sub(r"::h[0-9a-f]{16}$", "", d or k)))
    rows.sort(reverse=True)
    print("functions inlined at two or more places (DWARF inline records)")
    print(f"{'at most':>8} {'copies':>6} {'bytes':>7}  name  (at most: all bytes but the biggest copy's)")
    for saved, count, total, name in rows[:top]:
        print(f"{fmt_bytes(saved)} {count:>6} {fmt_bytes(total)}  {name}")


def figures(path):
    """(flash bytes, Counter of bytes by symbol name) of an ELF or of a file --record wrote.
    Unnamed constants are renumbered by every build: counted as one row."""
    counts = collections.Counter()
    with open(path, "rb") as f:
        is_elf = f.read(4) == b"\x7fELF"
    if is_elf:
        for _, size, _, name in symbols(path):
            counts["[anonymous constants]" if name.startswith(".L") else name] += size
        return sum(section_sizes(path).get(s, 0) for s in FLASH_SECTIONS), counts
    flash = None
    with open(path, encoding="utf-8") as f:
        for ln in f:
            ln = ln.rstrip("\n")
            if ln.startswith("#"):
                m = re.search(r"\bflash (\d+)", ln)
                if m:
                    flash = int(m.group(1))
                continue
            size, _, name = ln.partition("\t")
            if size.isdigit():
                counts[name] += int(size)
    if flash is None:
        sys.exit(f"{path}: not an ELF nor a file of --record (no '# ... flash N' line)")
    return flash, counts


def record(elf, out):
    flash, counts = figures(elf)
    try:
        commit = run(["git", "rev-parse", "HEAD"]).strip()
    except (subprocess.CalledProcessError, FileNotFoundError):
        commit = "unknown"
    with open(out, "w", encoding="utf-8") as f:
        f.write(f"# size baseline: commit {commit} flash {flash} (python3 tools/size-report.py --record)\n")
        for name, size in sorted(counts.items(), key=lambda c: (-c[1], c[0])):
            f.write(f"{size}\t{name}\n")
    print(f"{out}: flash {flash} B, {len(counts)} symbols, commit {commit}")


def diff(elf, base, top):
    fn, new = figures(elf)
    fo, old = figures(base)
    print(f"flash {fo} -> {fn} B ({fn - fo:+d})")
    ch = [(new[k] - old[k], k) for k in set(new) | set(old) if new[k] != old[k]]
    ch.sort(key=lambda c: -abs(c[0]))
    for d, k in ch[:top]:
        print(f"{d:+8d}  {old[k]:>7} -> {new[k]:<7} {k}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("elf", nargs="?", default=DEFAULT_ELF)
    ap.add_argument("-n", "--top", type=int, default=30, help="rows to print (default 30)")
    ap.add_argument("--depth", type=int, default=2, help="module path depth of the module totals")
    ap.add_argument("--no-groups", action="store_true", help="only the top symbols")
    ap.add_argument("--inlined", metavar="SYMBOL", help="break down the functions whose name contains SYMBOL")
    ap.add_argument("--inlined-depth", type=int, default=1, help="inline level for --inlined (default 1)")
    ap.add_argument("--baseline", metavar="ELF", help="print per-symbol differences to this image (or a --record file)")
    ap.add_argument("--record", metavar="FILE", help="write this image's per-symbol sizes to FILE (the size baseline)")
    ap.add_argument("--inline-sites", action="store_true", help="functions inlined at two or more places")
    a = ap.parse_args()
    if not os.path.exists(a.elf):
        sys.exit(f"{a.elf}: no such file (cargo build --release --target thumbv7em-none-eabihf)")
    if a.inline_sites:
        inline_sites(a.elf, a.top)
    elif a.inlined is not None:
        inlined(a.elf, a.inlined, a.top, a.inlined_depth)
    elif a.record:
        record(a.elf, a.record)
    elif a.baseline:
        diff(a.elf, a.baseline, a.top)
    else:
        report(a.elf, a.top, a.depth, not a.no_groups)


if __name__ == "__main__":
    main()
