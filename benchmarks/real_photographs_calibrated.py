"""Each method of the papers, both variants, on the eight real photographs in tests/data/real-images/.

Every method is told each photograph's FOV exactly: the papers' calibrated mode, `--fov-error 0`, with
no distortion model. This is the test Juang, Kim & Junkins made with their method on night-sky images
(7 of 10 identified). A solve is correct when its boresight is within 0.1 deg of the reference, wrong
when it is solved but farther off; the last row is the default pipeline told nothing (blind). Prints
the markdown table; `skyview bench --compare` runs the same (`skyview.bench.compare.run_real`) beside the
simulated comparison and writes docs/benchmarks.md's tables.

Run: SKYVIEW_CACHE=/tmp/svcache .venv/bin/python benchmarks/real_photographs_calibrated.py
(the triangle method builds a database for every photograph's exact FOV: minutes the first time).
"""

from __future__ import annotations

from skyview.bench.compare import run_real


def main() -> None:
    real = run_real()
    print("| method | variant | correct | wrong | inconclusive | time per image (median) |")
    print("|---|---|---|---|---|---|")
    for r in real["rows"]:
        print(f"| {r['method']} | {r['variant']} | {r['correct']} / {r['images']} | {r['wrong']} | "
              f"{r['inconclusive']} | {r['time_ms_median']:.0f} ms |", flush=True)


if __name__ == "__main__":
    main()
