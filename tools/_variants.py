"""The command line of the tools that run real logs under variants (``fragility.py``,
``degrade_logs.py``): each (log, variant) runs in a subprocess of the tool (``--one LOG VARIANT``)
that writes ``OUT/LOG_VARIANT/summary.json``; a row of the tool's table is printed as each ends
and the whole table at the end. A run that fails prints its last error line and leaves its
``stderr.txt``."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path


def variants_main(
    doc: str,
    script: str,
    logs: list[str],
    variants: list[str],
    default_logs: list[str],
    default_variants: list[str],
    run_one: Callable[[str, str, Path], dict],
    table: Callable[[list[dict]], str],
) -> None:
    """Parse the command line of ``script`` (its module docstring ``doc``) and run it."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--logs", nargs="+", default=default_logs, choices=sorted(logs))
    ap.add_argument("--variants", nargs="+", default=default_variants, choices=list(variants))
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--force", action="store_true", help="run again where summary.json exists")
    ap.add_argument("--one", nargs=2, metavar=("LOG", "VARIANT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print(json.dumps(run_one(args.one[0], args.one[1], args.out)))
        return
    rows = []
    for log in args.logs:
        for v in args.variants:
            d = args.out / f"{log}_{v}"
            if args.force or not (d / "summary.json").exists():
                cmd = [sys.executable, script, "--one", log, v, "--out", str(d)]
                r = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                if r.returncode:
                    last = (r.stderr.strip().splitlines() or ["no error output"])[-1]
                    print(f"| {log} | {v} | FAILED: {last} |", flush=True)
                    d.mkdir(parents=True, exist_ok=True)
                    (d / "stderr.txt").write_text(r.stderr)
                    continue
            rows.append(json.loads((d / "summary.json").read_text()))
            print(table(rows[-1:]).splitlines()[-1], flush=True)
    print(table(rows))
