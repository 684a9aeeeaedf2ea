"""Hydra configuration tree of qtl, installed as the package ``qtl.configs``."""
