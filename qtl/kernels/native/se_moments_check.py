"""The build's smoke check of the native SE-kernel moments against the fused torch code (`SEKernelMoments`).

Apart from `se_moments.py`, which `qtl.kernels.moments` imports: this module imports the moments.
"""

from __future__ import annotations

import torch

from qtl.kernels.engine import Engine
from qtl.kernels.moments import SEKernelMoments
from qtl.kernels.native.se_moments import SEMomentsLibrary, load_se_moments, se_kernel_moments

# The smoke check's tolerance (relative, float64): the kernel agrees with torch to ~1e-15.
CHECK_RTOL = 1e-12


def check_against_torch(library: SEMomentsLibrary | None = None, error: type[Exception] = RuntimeError) -> None:
    """Values and gradients of the compiled moments equal the fused torch code on a small odd-shaped problem.

    Gaussian inputs `2 x 3 x D` against a GP (E = 3, n = 7, D = 5, with K⁻¹, constants `3 x ...`)
    and an RBF network (E = 2, constants `2 x 1 x ...` whose weights need gradients); raises
    ``error`` (e.g. ``build.BuildError``; a RuntimeError by default) when they disagree beyond CHECK_RTOL.
    """
    library = library or load_se_moments()
    gen = torch.Generator().manual_seed(0)
    f64 = torch.float64
    root = 0.4 * torch.randn(2, 3, 5, 5, generator=gen, dtype=f64)
    mean = (0.5 * torch.randn(2, 3, 5, generator=gen, dtype=f64)).requires_grad_()
    cov = (root @ root.mT + 0.05 * torch.eye(5, dtype=f64)).requires_grad_()
    # (E, the constants' batch, with K⁻¹, β needs a gradient): the GP as in policy search (the forward
    # keeps G_A, G_B), the GP with all gradients and an RBF network (backward recomputes the sums).
    for num_out, lead, with_k_inv, beta_grad in (
        (3, (3,), True, False),
        (3, (3,), True, True),
        (2, (2, 1), False, True),
    ):
        inputs = torch.randn(*lead, 7, 5, generator=gen, dtype=f64).requires_grad_()
        beta = torch.randn(*lead, num_out, 7, generator=gen, dtype=f64).requires_grad_(beta_grad)
        ls = (0.7 + torch.rand(*lead, num_out, 5, generator=gen, dtype=f64)).requires_grad_()
        sf2 = (0.5 + torch.rand(num_out, generator=gen, dtype=f64)).requires_grad_()
        k_inv = None
        if with_k_inv:
            k_root = torch.randn(*lead, num_out, 7, 7, generator=gen, dtype=f64)
            k_inv = 0.1 * (k_root @ k_root.mT)
        m = SEKernelMoments(inputs, beta, ls, sf2, k_inv)
        leaves = tuple(t for t in (mean, cov, inputs, beta, ls, sf2) if t.requires_grad)
        probes = [torch.randn(s, generator=gen, dtype=f64) for s in ((2, 3, num_out), (2, 3, num_out, num_out))]
        probes.append(torch.randn(2, 3, 5, num_out, generator=gen, dtype=f64))
        want = m._fused_call(mean, cov, Engine(moments="fused"))
        got = list(se_kernel_moments(mean, cov, m.inputs, m.beta, m.inv_ls, m.log_sf2, m.weights, library))
        if with_k_inv:
            got[1] = got[1] + torch.diag_embed(sf2)
        results = []
        for outs in (got, want):
            loss = sum((o * p).sum() for o, p in zip(outs, probes, strict=True))
            results.append((*outs, *torch.autograd.grad(loss, leaves, retain_graph=True)))
        for value, reference in zip(*results, strict=True):
            err, scale = (value - reference).abs().max().item(), reference.abs().max().item()
            if not err <= CHECK_RTOL * scale:
                raise error(f"the compiled SE-kernel moments disagree with torch (max error {err:.3g})")
