"""The seed's section 6 sensitivity study in one command, ending with the report.

    python workflows/sensitivity_section6.py [-o OUTDIR] [--workers N] [--scheduler ADDRESS]

Runs workflows/sensitivity_section6.yaml (Coulomb 12-24 degrees and Pouliquen d = 0.5-3 m,
three release volumes: 39 members) with ``avflow ensemble``, then ``avflow report``.
Resumable: a second call reuses the members already in OUTDIR. Equivalent to

    avflow ensemble workflows/sensitivity_section6.yaml -o OUTDIR --report
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from avflow.cli import main as avflow

ENSEMBLE = Path(__file__).resolve().with_name("sensitivity_section6.yaml")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default="sensitivity_section6",
                        help="output folder (default: ./sensitivity_section6)")
    parser.add_argument("--workers", help="local worker processes (0: no dask)")
    parser.add_argument("--scheduler", help="address or scheduler file of a dask cluster")
    args = parser.parse_args(argv)
    command = ["ensemble", str(ENSEMBLE), "-o", args.output]
    if args.workers is not None:
        command += ["--workers", args.workers]
    if args.scheduler:
        command += ["--scheduler", args.scheduler]
    code = avflow(command)
    if code == 2:
        return code
    report = avflow(["report", args.output])  # also when some members failed
    return code or report


if __name__ == "__main__":
    sys.exit(main())
