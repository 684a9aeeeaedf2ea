"""qtl: PILCO with qualitative transfer of GP hyper-parameters between related tasks."""

__version__ = "0.1.0"
