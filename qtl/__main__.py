"""``python -m qtl``: the same as ``qtl-train``."""

from qtl.train import main

main()
