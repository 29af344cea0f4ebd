"""`imitrl frozenlake` against the plain gymnasium + numpy script, side by side.

Each command runs as a fresh process (imports included) on the same machine, one
after another, best of ``--repeats``:

* plain:    python benchmarks/frozenlake_plain.py   (the section's code, same experiments)
* faithful: imitrl frozenlake                       (the section's digits)
* batched:  imitrl frozenlake --protocol batched    (100x the evaluation episodes)

    python benchmarks/frozenlake_timing.py              # full run, refreshes README
    python benchmarks/frozenlake_timing.py --quick      # smoke run, into a temporary directory
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time

import _report

NAME = "frozenlake_timing"


def wall(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> dict:
    parser = _report.parser(__doc__)
    parser.add_argument("--repeats", type=int, default=3, help="best of (1 with --quick)")
    args = parser.parse_args(argv)
    out_dir = _report.destination(NAME, quick=args.quick, out=args.out)
    repeats = 1 if args.quick else args.repeats
    extra = ["--no-exercises"] if args.quick else []
    # the plain script reproduces sections 1-7 and the exercises: the study's IRL section
    # (8) has no counterpart there, so it is left out of the comparison
    ours = [*extra, "--no-irl"]
    if args.quick:  # a smoke run of the command lines: small counts (timings not comparable)
        ours += ["--sweep-datasets", "2", "--eval-episodes", "200", "--chain-samples", "2000"]
    py = sys.executable
    with tempfile.TemporaryDirectory() as tmp:
        commands = {
            "plain gymnasium + numpy script": [
                py,
                str(_report.HERE / "frozenlake_plain.py"),
                "--out",
                f"{tmp}/plain",
                *extra,
            ],
            "imitrl frozenlake (faithful)": [
                py,
                "-m",
                "imitrl",
                "frozenlake",
                "--out",
                f"{tmp}/faithful",
                "--no-progress",
                *ours,
            ],
            "imitrl frozenlake --protocol batched": [
                py,
                "-m",
                "imitrl",
                "frozenlake",
                "--protocol",
                "batched",
                "--out",
                f"{tmp}/batched",
                "--no-progress",
                *ours,
            ],
        }
        if args.quick:  # the batched protocol's command line is covered by the study tests
            del commands["imitrl frozenlake --protocol batched"]
        times = {name: [] for name in commands}
        for _ in range(repeats):  # interleaved, so load changes hit every command alike
            for name, cmd in commands.items():
                times[name].append(wall(cmd))
    best = {name: min(t) for name, t in times.items()}
    plain = best["plain gymnasium + numpy script"]
    rows = []
    for name, t in best.items():
        rows.append([name, f"{t:.1f} s", f"{plain / t:.2f}x"])
        print(f"{name:<40} {t:6.1f} s   {plain / t:.2f}x the plain script's speed")
    scope = "without exercises" if args.quick else "full study, exercises included"
    md = (
        f"Wall time of each command as a fresh process, {scope}, best of {repeats}; "
        "the batched protocol evaluates 100x more episodes.\n\n"
        + _report.table(["command", "wall time", "speed vs plain"], rows)
    )
    payload = {"repeats": repeats, "quick": args.quick, "times": times, "best": best}
    print("results:", _report.write(NAME, payload, md, out_dir=out_dir))
    return payload


if __name__ == "__main__":
    main()
