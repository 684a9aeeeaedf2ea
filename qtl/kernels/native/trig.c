/* qtl native kernel: exact trigonometric moments of a Gaussian (PILCO's gTrig and gSat), forward and
 * reverse mode, one call each over a batch.
 *
 * Maths. For angles φ ~ N(m, Σ) (float64), with v_i = Σ_ii, damp_i = exp(−v_i/2):
 *   E sin φ_i = damp_i sin m_i,   E cos φ_i = damp_i cos m_i,
 * and for a pair (i, j), with lo = −(v_i + v_j)/2, σ = Σ_ij, d = m_i − m_j, p = m_i + m_j,
 *   G = e^{lo}(e^{σ} − 1),   S = e^{lo}(e^{−σ} − 1),
 *   cov[sin φ_i, sin φ_j] = ½(G cos d − S cos p),   cov[sin φ_i, cos φ_j] = ½(G sin d + S sin p),
 *   cov[cos φ_i, sin φ_j] = ½(S sin p − G sin d),   cov[cos φ_i, cos φ_j] = ½(G cos d + S cos p).
 * G and S are formed as sign · expm1(sign s) · exp(lo + max(s, 0)) with sign = −1 for s >= 0, else 1
 * (|s| <= −lo by Cauchy–Schwarz): no overflow for large variances, and exactly 0 for a zero covariance.
 * Derivatives: ∂F/∂lo = F and ∂F/∂s = e^{lo + max(s,0)} (expm1(sign s) + 1) + [s > 0] F.
 *
 * Angle features (qtl.features.AngleFeatures.moments, fused branch): x ~ N(μ `D`, Σ `D x D`) with
 * angles at dims a_k (K of them) and the O other dims kept; y = [x_other, sin x_a1, cos x_a1, …]
 * (`E = O + 2K`). Outputs per item: mean `E`, cov `E x E` (symmetrized as 0.5 (C + Cᵀ)), the gain
 * `D x E` (unit columns for the kept dims, (E cos, −E sin) on the angle rows) and cross_cov = Σ gain.
 *
 * Sine squashing (qtl.policies.squash._squash_terms, fused branch): z ~ N(μ `F`, Σ `F x F`),
 * u_f = Σ_q w_qf sin(c_q z_f) with c = (1, 3) and w = (9/8, 1/8) u_max: φ = [z, 3z] (2F angles);
 * outputs mean `F`, cov `F x F` (Σ_qr w_qf w_rg cov[sin φ_qf, sin φ_rg], symmetrized) and the slope
 * E[∂u_f/∂z_f] = Σ_q c_q w_qf E cos φ_qf `F`.
 *
 * Backward: hand-derived reverse mode of exactly those forward formulae, in the same convention as
 * autograd through the fused torch code (the gradient for Σ is not symmetrized: Σ_ij and Σ_ji each
 * get what depends on them). Upstream gradients may be NULL (zero).
 *
 * Layout: input item b starts at element offset off_mean[b] / off_cov[b] (broadcast inputs repeat an
 * offset); each matrix is row-major and contiguous; outputs and input gradients are dense per item.
 * The reference twin is the fused torch code; see qtl/kernels/native/trig.py.
 * Build: with the other sources of this directory (qtl/kernels/native/build.py).
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

/* sign expm1(sign s) e^{lo + max(s,0)}, with e = expm1(sign s) and x = e^{lo + max(s,0)} returned. */
static inline double exp_expm1(double lo, double s, double *e, double *x) {
    const double sign = s >= 0.0 ? -1.0 : 1.0;
    *e = expm1(s * sign);
    *x = exp(lo + (s > 0.0 ? s : 0.0));
    return *e * *x * sign;
}

/* ∂F/∂s of exp_expm1 from its value and factors (∂F/∂lo is the value itself). */
static inline double exp_expm1_ds(double s, double value, double e, double x) {
    return x * (e + 1.0) + (s > 0.0 ? value : 0.0);
}

static inline double get(const double *g, ptrdiff_t i) { return g ? g[i] : 0.0; }

/* ---------------------------------------------------------------- angle features */

int qtl_trig_features_forward(int64_t items, int64_t dim, int64_t num, const int64_t *angles, const int64_t *others,
                              const double *mean, const double *cov, const int64_t *off_mean, const int64_t *off_cov,
                              double *out_mean, double *out_cov, double *cross_cov, double *gain) {
    const int64_t nother = dim - num, width = nother + 2 * num;
    for (int64_t b = 0; b < items; ++b) {
        const double *mu = mean + off_mean[b], *sg = cov + off_cov[b];
        double *om = out_mean + b * width, *oc = out_cov + b * width * width;
        double *xc = cross_cov + b * dim * width, *gn = gain + b * dim * width;
        memset(gn, 0, (size_t)(dim * width) * sizeof(double));
        for (int64_t o = 0; o < nother; ++o) {
            om[o] = mu[others[o]];
            gn[others[o] * width + o] = 1.0;
        }
        for (int64_t k = 0; k < num; ++k) {
            const int64_t a = angles[k];
            const double damp = exp(-0.5 * sg[a * dim + a]);
            const double es = sin(mu[a]) * damp, ec = cos(mu[a]) * damp;
            om[nother + 2 * k] = es;
            om[nother + 2 * k + 1] = ec;
            gn[a * width + nother + 2 * k] = ec;
            gn[a * width + nother + 2 * k + 1] = -es;
        }
        /* cross_cov = Σ gain: the kept columns of Σ, then Σ[:, a_k] (E cos, −E sin). */
        for (int64_t i = 0; i < dim; ++i) {
            for (int64_t o = 0; o < nother; ++o) xc[i * width + o] = sg[i * dim + others[o]];
            for (int64_t k = 0; k < num; ++k) {
                const int64_t a = angles[k];
                xc[i * width + nother + 2 * k] = sg[i * dim + a] * gn[a * width + nother + 2 * k];
                xc[i * width + nother + 2 * k + 1] = sg[i * dim + a] * gn[a * width + nother + 2 * k + 1];
            }
        }
        /* Kept block, and the kept–trig blocks (rows of cross_cov, already symmetric). */
        for (int64_t o = 0; o < nother; ++o) {
            for (int64_t p = 0; p < nother; ++p)
                oc[o * width + p] = 0.5 * (sg[others[o] * dim + others[p]] + sg[others[p] * dim + others[o]]);
            for (int64_t t = nother; t < width; ++t) oc[o * width + t] = oc[t * width + o] = xc[others[o] * width + t];
        }
        /* Trig block, before symmetrizing: pair (i, j) fills rows (sin_i, cos_i) x columns (sin_j, cos_j). */
        for (int64_t i = 0; i < num; ++i) {
            const int64_t ai = angles[i];
            for (int64_t j = 0; j < num; ++j) {
                const int64_t aj = angles[j];
                const double lo = -0.5 * (sg[ai * dim + ai] + sg[aj * dim + aj]), s = sg[ai * dim + aj];
                double e, x;
                const double g = exp_expm1(lo, s, &e, &x), h = exp_expm1(lo, -s, &e, &x);
                const double d = mu[ai] - mu[aj], p = mu[ai] + mu[aj];
                const double cd = cos(d), sd = sin(d), cp = cos(p), sp = sin(p);
                double *row_s = oc + (nother + 2 * i) * width + nother + 2 * j, *row_c = row_s + width;
                row_s[0] = 0.5 * (g * cd) - 0.5 * (h * cp);
                row_s[1] = 0.5 * (g * sd) + 0.5 * (h * sp);
                row_c[0] = 0.5 * (h * sp) - 0.5 * (g * sd);
                row_c[1] = 0.5 * (g * cd) + 0.5 * (h * cp);
            }
        }
        for (int64_t r = nother; r < width; ++r)
            for (int64_t c = r; c < width; ++c) oc[r * width + c] = oc[c * width + r] = 0.5 * (oc[r * width + c] + oc[c * width + r]);
    }
    return 0;
}

int qtl_trig_features_backward(int64_t items, int64_t dim, int64_t num, const int64_t *angles, const int64_t *others,
                               const double *mean, const double *cov, const int64_t *off_mean, const int64_t *off_cov,
                               const double *g_mean, const double *g_cov, const double *g_cross, const double *g_gain,
                               double *grad_mean, double *grad_cov) {
    const int64_t nother = dim - num, width = nother + 2 * num;
    for (int64_t b = 0; b < items; ++b) {
        const double *mu = mean + off_mean[b], *sg = cov + off_cov[b];
        const ptrdiff_t om = b * width, oc = b * width * width, ox = b * dim * width;
        double *gm = grad_mean + b * dim, *gs = grad_cov + b * dim * dim;
        memset(gm, 0, (size_t)dim * sizeof(double));
        memset(gs, 0, (size_t)(dim * dim) * sizeof(double));
        /* ∂/∂C of V = 0.5 (C + Cᵀ): 0.5 gV + 0.5 gVᵀ. */
#define GC(r, c) (0.5 * get(g_cov, oc + (r) * width + (c)) + 0.5 * get(g_cov, oc + (c) * width + (r)))
        for (int64_t o = 0; o < nother; ++o) gm[others[o]] = get(g_mean, om + o);
        /* Through cross_cov = Σ gain (with the kept rows of cross_cov read by the output covariance):
         * ∂Σ[i, other_o] = gX'[i, o]; ∂Σ[i, a_k] = gX'[i, sin_k] E cos − gX'[i, cos_k] E sin;
         * ∂gain[a_k, ·] = Σ_i Σ[i, a_k] gX'[i, ·]. */
        for (int64_t k = 0; k < num; ++k) {
            const int64_t a = angles[k], cs = nother + 2 * k, cc = cs + 1;
            const double damp = exp(-0.5 * sg[a * dim + a]), sn = sin(mu[a]), cn = cos(mu[a]);
            const double es = sn * damp, ec = cn * damp;
            double g_es = get(g_mean, om + cs), g_ec = get(g_mean, om + cc);
            double g_slope_s = get(g_gain, ox + a * width + cs), g_slope_c = get(g_gain, ox + a * width + cc);
            for (int64_t i = 0; i < dim; ++i) {
                double gx_s = get(g_cross, ox + i * width + cs), gx_c = get(g_cross, ox + i * width + cc);
                for (int64_t o = 0; o < nother; ++o) {
                    if (others[o] != i) continue;
                    gx_s += GC(o, cs) + GC(cs, o);
                    gx_c += GC(o, cc) + GC(cc, o);
                }
                gs[i * dim + a] += gx_s * ec + gx_c * -es;
                g_slope_s += sg[i * dim + a] * gx_s;
                g_slope_c += sg[i * dim + a] * gx_c;
            }
            g_ec += g_slope_s;
            g_es -= g_slope_c;
            gm[a] += cn * (g_es * damp) - sn * (g_ec * damp);
            gs[a * dim + a] += -0.5 * ((g_es * sn + g_ec * cn) * damp);
        }
        for (int64_t o = 0; o < nother; ++o)
            for (int64_t i = 0; i < dim; ++i) {
                double gx = get(g_cross, ox + i * width + o);
                for (int64_t p = 0; p < nother; ++p)
                    if (others[p] == i) gx += GC(p, o);
                gs[i * dim + others[o]] += gx;
            }
        /* The trig block, pair by pair. */
        for (int64_t i = 0; i < num; ++i) {
            const int64_t ai = angles[i], si = nother + 2 * i;
            for (int64_t j = 0; j < num; ++j) {
                const int64_t aj = angles[j], sj = nother + 2 * j;
                const double gss = GC(si, sj), gsc = GC(si, sj + 1), gcs = GC(si + 1, sj), gcc = GC(si + 1, sj + 1);
                const double lo = -0.5 * (sg[ai * dim + ai] + sg[aj * dim + aj]), s = sg[ai * dim + aj];
                double eg, xg, eh, xh;
                const double g = exp_expm1(lo, s, &eg, &xg), h = exp_expm1(lo, -s, &eh, &xh);
                const double d = mu[ai] - mu[aj], p = mu[ai] + mu[aj];
                const double cd = cos(d), sd = sin(d), cp = cos(p), sp = sin(p);
                const double g_g = 0.5 * (cd * (gss + gcc) + sd * (gsc - gcs));
                const double g_h = 0.5 * (cp * (gcc - gss) + sp * (gsc + gcs));
                const double g_d = 0.5 * g * (cd * (gsc - gcs) - sd * (gss + gcc));
                const double g_p = 0.5 * h * (cp * (gsc + gcs) - sp * (gcc - gss));
                gm[ai] += g_d + g_p;
                gm[aj] += g_p - g_d;
                gs[ai * dim + aj] += exp_expm1_ds(s, g, eg, xg) * g_g - exp_expm1_ds(-s, h, eh, xh) * g_h;
                const double g_lo = g * g_g + h * g_h;
                gs[ai * dim + ai] -= 0.5 * g_lo;
                gs[aj * dim + aj] -= 0.5 * g_lo;
            }
        }
#undef GC
    }
    return 0;
}

/* ---------------------------------------------------------------- sine squashing */

static const double FREQ[2] = {1.0, 3.0};
static const double MIX[2] = {9.0 / 8.0, 1.0 / 8.0};

int qtl_sin_squash_forward(int64_t items, int64_t num, const double *bound, const double *mean, const double *cov,
                           const int64_t *off_mean, const int64_t *off_cov, double *out_mean, double *out_cov,
                           double *slope) {
    for (int64_t b = 0; b < items; ++b) {
        const double *mu = mean + off_mean[b], *sg = cov + off_cov[b];
        double *om = out_mean + b * num, *oc = out_cov + b * num * num, *sl = slope + b * num;
        for (int64_t f = 0; f < num; ++f) {
            om[f] = 0.0;
            sl[f] = 0.0;
            for (int q = 0; q < 2; ++q) {
                const double m = FREQ[q] * mu[f], damp = exp(-0.5 * (FREQ[q] * FREQ[q] * sg[f * num + f]));
                const double w = MIX[q] * bound[f];
                om[f] += sin(m) * damp * w;
                sl[f] += cos(m) * damp * (FREQ[q] * w);
            }
        }
        for (int64_t f = 0; f < num; ++f)
            for (int64_t g = 0; g < num; ++g) {
                double acc = 0.0;
                for (int q = 0; q < 2; ++q)
                    for (int r = 0; r < 2; ++r) {
                        const double vf = FREQ[q] * FREQ[q] * sg[f * num + f], vg = FREQ[r] * FREQ[r] * sg[g * num + g];
                        const double lo = -0.5 * (vf + vg), s = FREQ[q] * FREQ[r] * sg[f * num + g];
                        const double m_f = FREQ[q] * mu[f], m_g = FREQ[r] * mu[g];
                        double e, x;
                        const double gg = exp_expm1(lo, s, &e, &x), hh = exp_expm1(lo, -s, &e, &x);
                        const double sin_cov = 0.5 * (gg * cos(m_f - m_g)) - 0.5 * (hh * cos(m_f + m_g));
                        acc += sin_cov * ((MIX[q] * bound[f]) * (MIX[r] * bound[g]));
                    }
                oc[f * num + g] = acc;
            }
        for (int64_t f = 0; f < num; ++f)
            for (int64_t g = f; g < num; ++g) oc[f * num + g] = oc[g * num + f] = 0.5 * (oc[f * num + g] + oc[g * num + f]);
    }
    return 0;
}

int qtl_sin_squash_backward(int64_t items, int64_t num, const double *bound, const double *mean, const double *cov,
                            const int64_t *off_mean, const int64_t *off_cov, const double *g_mean,
                            const double *g_cov, const double *g_slope, double *grad_mean, double *grad_cov) {
    for (int64_t b = 0; b < items; ++b) {
        const double *mu = mean + off_mean[b], *sg = cov + off_cov[b];
        const ptrdiff_t om = b * num, oc = b * num * num;
        double *gm = grad_mean + b * num, *gs = grad_cov + b * num * num;
        memset(gs, 0, (size_t)(num * num) * sizeof(double));
        for (int64_t f = 0; f < num; ++f) {
            gm[f] = 0.0;
            for (int q = 0; q < 2; ++q) {
                const double m = FREQ[q] * mu[f], damp = exp(-0.5 * (FREQ[q] * FREQ[q] * sg[f * num + f]));
                const double w = MIX[q] * bound[f], sn = sin(m), cn = cos(m);
                const double g_es = w * get(g_mean, om + f), g_ec = FREQ[q] * w * get(g_slope, om + f);
                gm[f] += FREQ[q] * (cn * (g_es * damp) - sn * (g_ec * damp));
                gs[f * num + f] += FREQ[q] * FREQ[q] * (-0.5 * ((g_es * sn + g_ec * cn) * damp));
            }
        }
        if (!g_cov) continue;
        for (int64_t f = 0; f < num; ++f)
            for (int64_t g = 0; g < num; ++g) {
                const double g_pair = 0.5 * g_cov[oc + f * num + g] + 0.5 * g_cov[oc + g * num + f];
                for (int q = 0; q < 2; ++q)
                    for (int r = 0; r < 2; ++r) {
                        const double vf = FREQ[q] * FREQ[q] * sg[f * num + f], vg = FREQ[r] * FREQ[r] * sg[g * num + g];
                        const double lo = -0.5 * (vf + vg), s = FREQ[q] * FREQ[r] * sg[f * num + g];
                        const double m_f = FREQ[q] * mu[f], m_g = FREQ[r] * mu[g];
                        double eg, xg, eh, xh;
                        const double gg = exp_expm1(lo, s, &eg, &xg), hh = exp_expm1(lo, -s, &eh, &xh);
                        const double d = m_f - m_g, p = m_f + m_g;
                        const double g_sc = g_pair * ((MIX[q] * bound[f]) * (MIX[r] * bound[g]));
                        const double g_g = 0.5 * cos(d) * g_sc, g_h = -0.5 * cos(p) * g_sc;
                        const double g_d = -0.5 * gg * sin(d) * g_sc, g_p = 0.5 * hh * sin(p) * g_sc;
                        gm[f] += FREQ[q] * (g_d + g_p);
                        gm[g] += FREQ[r] * (g_p - g_d);
                        gs[f * num + g] += FREQ[q] * FREQ[r] *
                                           (exp_expm1_ds(s, gg, eg, xg) * g_g - exp_expm1_ds(-s, hh, eh, xh) * g_h);
                        const double g_lo = gg * g_g + hh * g_h;
                        gs[f * num + f] -= 0.5 * FREQ[q] * FREQ[q] * g_lo;
                        gs[g * num + g] -= 0.5 * FREQ[r] * FREQ[r] * g_lo;
                    }
            }
    }
    return 0;
}
