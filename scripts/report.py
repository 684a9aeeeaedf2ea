"""The paper's tables and figures from an experiment directory: ``qtl-report`` (:mod:`qtl.report.cli`) as a script.

    python scripts/report.py runs/cartpole [--out DIR] [--finished-only] [--record-reference] [--export DIR]
"""

from __future__ import annotations

from qtl.report.cli import main

if __name__ == "__main__":
    main()
