"""Which lines of dbdjax become the kernels of a compiled step, read from XLA's optimised HLO.

On the GPU a step's time is its number of kernels (docs/brax_comparison.md, session 46:
1,456 kernels per humanoid step at 1.9 us each, the GPU busy throughout). XLA writes the program it
runs, after fusion, with `XLA_FLAGS=--xla_dump_to=DIR`; this script reads one such
`*after_optimizations.txt` (plain or .gz) and counts its kernels per step: every fusion, custom call
and copy, times the trip counts of the loops around it (XLA's `known_trip_count`; every branch of
a conditional counted, so an upper bound where there are branches), then groups them by the
innermost line of the source that made each (the HLO's stack frames), and by every function on
that stack (`per_function`: a stage's kernels with those of what it calls, e.g. the solver's
sweeps against the whole step). It needs no GPU: a
dump made on one (`benchmarks/results/hlo/`, session 46's H200) can be read anywhere, and a CPU
dump of the same program is read the same way (XLA:CPU fuses differently).

    python benchmarks/hlo_kernels.py benchmarks/results/hlo/dbd_humanoid_4096_h200.txt.gz --steps 10

--steps: the physics steps in the dumped program (kernel_trace.py traces a scan of 10).
--within: each kernel is attributed to its innermost frame in the source files whose path holds
this text (default "dbdjax/"); kernels with no such frame are counted as "(outside)". For Brax's
programs, --within brax/.
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import re
from pathlib import Path

KERNELS = {"fusion", "custom-call", "copy", "copy-start", "sort", "scatter", "gather", "convolution", "dot"}
HEADER = re.compile(r"^(ENTRY )?%(\S+) \(.*\) -> .* \{$")
INSTRUCTION = re.compile(r"^\s*(?:ROOT )?%(\S+) = (.*?) ([a-z][a-z0-9\-]*)\((.*)$")
# The functions of dbdjax/math.py that bind its written-out products as primitives.
PASSED_OVER = "_written_out_primitive."
TRIP_COUNT = re.compile(r'known_trip_count":\{"n":"(\d+)"')


def read(path: Path) -> str:
    data = path.read_bytes()
    return (gzip.decompress(data) if data[:2] == b"\x1f\x8b" else data).decode()


def tables(text: str) -> tuple[dict, dict]:
    """The HLO's stack frame table: frame id -> (location id, parent frame id, 0 for none), and
    location id -> (file, function, line). The dump prints a frame's parent_frame_id as the parent's
    id plus one (1 where it has none): calls <module> -> f -> g, numbered 1, 2, 3, print
    `parent_frame_id=3` on g's frame, f's id plus one."""
    sections: dict[str, dict[int, str]] = {}
    current = None
    for line in text.splitlines():
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            current = sections.setdefault(line, {})
        elif current is not None and line[:1].isdigit():
            key, _, value = line.partition(" ")
            current[int(key)] = value
        elif current is not None and line.strip():
            current = None
    files = {k: v.strip('"') for k, v in sections.get("FileNames", {}).items()}
    functions = {k: v.strip('"') for k, v in sections.get("FunctionNames", {}).items()}
    field = lambda text, name: int(re.search(rf"{name}=(\d+)", text).group(1))  # noqa: E731
    locations = {k: (files[field(v, "file_name_id")], functions[field(v, "function_name_id")], field(v, "line"))
                 for k, v in sections.get("FileLocations", {}).items()}  # fmt: skip
    frames = {k: (field(v, "file_location_id"), field(v, "parent_frame_id") - 1)
              for k, v in sections.get("StackFrames", {}).items()}  # fmt: skip
    return frames, locations


def computations(text: str) -> tuple[dict[str, list[tuple[str, str, str]]], str]:
    """Every computation's instructions (name, opcode, rest of the line), and the entry's name."""
    result, entry, current = {}, None, None
    for line in text.splitlines():
        header = HEADER.match(line)
        if header:
            current = result.setdefault(header.group(2), [])
            entry = header.group(2) if header.group(1) else entry
        elif line == "}":
            current = None
        elif current is not None:
            match = INSTRUCTION.match(line)
            if match:
                current.append((match.group(1), match.group(3), match.group(4)))
    return result, entry


def _frames_within(rest: str, frames: dict, locations: dict, within: str):
    """The stack frames of an instruction in files whose path holds `within`, innermost first, as
    (path from `within` on, line, function) (the frames of `math`'s primitive machinery passed over)."""
    match = re.search(r"stack_frame_id=(\d+)", rest)
    frame = int(match.group(1)) if match else 0
    seen = set()
    while frame in frames and frame not in seen:
        seen.add(frame)
        location, parent = frames[frame]
        file, function, line = locations[location]
        if within in file and not function.startswith(PASSED_OVER):
            yield file[file.index(within) :], line, function
        frame = parent


def source(rest: str, frames: dict, locations: dict, within: str) -> str:
    """The innermost frame in a file whose path holds `within`, as "path:line function". The
    frames of `math`'s primitive machinery (every written-out product binds there) are passed
    over for the line that called the product."""
    for path, line, function in _frames_within(rest, frames, locations, within):
        return f"{path}:{line} {function}"
    return "(outside)"


def functions(rest: str, frames: dict, locations: dict, within: str) -> set[str]:
    """Every function on the instruction's stack in a file whose path holds `within`, as
    "path function" (each once, however many of its lines the stack passes through)."""
    return {f"{path} {function}" for path, _, function in _frames_within(rest, frames, locations, within)}


def count(path: Path, steps: int, within: str) -> dict:
    text = read(path)
    frames, locations = tables(text)
    bodies, entry = computations(text)
    per_source: collections.Counter = collections.Counter()
    per_function: collections.Counter = collections.Counter()
    per_kind: collections.Counter = collections.Counter()
    unknown_trips = []

    def walk(name: str, times: int) -> None:
        for instruction, opcode, rest in bodies[name]:
            if opcode == "while":
                trip = TRIP_COUNT.search(rest)
                if not trip:
                    unknown_trips.append(instruction)
                trips = int(trip.group(1)) if trip else 1
                walk(re.search(r"body=%(\S+?)[,\s]", rest).group(1), times * trips)
                walk(re.search(r"condition=%(\S+?)[,\s]", rest).group(1), times * trips)
            elif opcode == "conditional":
                for branch in re.findall(r"%([\w.\-]+)", re.search(r"branch_computations=\{([^}]*)\}", rest).group(1)):
                    walk(branch, times)  # every branch counted: an upper bound
            elif opcode == "call":
                walk(re.search(r"to_apply=%(\S+?)[,\s]", rest).group(1), times)
            elif opcode in KERNELS:
                per_source[source(rest, frames, locations, within)] += times
                per_function.update(dict.fromkeys(functions(rest, frames, locations, within), times))
                kind = re.search(r"kind=(k\w+)", rest)
                per_kind[f"{opcode} {kind.group(1)}" if kind else opcode] += times

    walk(entry, 1)
    total = sum(per_source.values())
    per_file: collections.Counter = collections.Counter()
    for where, n in per_source.items():
        per_file[where.split(":")[0]] += n
    return {
        "hlo": path.name,
        "steps": steps,
        "kernels_per_step": round(total / steps, 1),
        "loops_without_known_trip_count": unknown_trips,
        "per_file": {k: round(v / steps, 1) for k, v in per_file.most_common()},
        "per_kind": {k: round(v / steps, 1) for k, v in per_kind.most_common()},
        "per_source_line": {k: round(v / steps, 1) for k, v in per_source.most_common()},
        # inclusive: a kernel counts for every function on its stack (a stage's share of the step)
        "per_function": {k: round(v / steps, 1) for k, v in per_function.most_common()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("hlo", type=Path, nargs="+", help="*after_optimizations.txt, plain or .gz")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--within", default="dbdjax/")
    parser.add_argument("--top", type=int, default=30)
    parser.add_argument("--out", type=Path, help="write the counts here (JSON)")
    args = parser.parse_args()
    results = [count(path, args.steps, args.within) for path in args.hlo]
    for result in results:
        print(f"{result['hlo']}: {result['kernels_per_step']} kernels per step")
        print("  per file:", ", ".join(f"{k} {v}" for k, v in result["per_file"].items()))
        for where, n in list(result["per_source_line"].items())[: args.top]:
            print(f"  {n:8.1f}  {where}")
        print("  per function, with what it calls:")
        for where, n in list(result["per_function"].items())[: args.top]:
            print(f"  {n:8.1f}  {where}")
    if args.out:
        args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
