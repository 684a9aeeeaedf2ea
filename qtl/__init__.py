"""qtl: PILCO with qualitative transfer of GP hyper-parameters between related tasks."""

__version__ = "1.0.0"
