/* qtl native kernel: the RBF network policy (MC-PILCO's sum of Gaussians) at a batch of points, and its gradients.
 *
 * Maths (float64). Points x_p `D` (p < M), centres c_s `D` (s < N), weights w_sf, inverse squared
 * lengthscales a_fd = ℓ_fd⁻² (f < F), and an optional mask m_ps (basis dropout, its 1/(1 − p) folded in):
 *   k_fps = m_ps exp(−½ Σ_d a_fd (x_pd − c_sd)²)
 *   u_pf  = Σ_s w_sf k_fps                                            (forward; k kept for backward)
 * and, for an upstream gradient g_pf, with h_fps = g_pf w_sf k_fps:
 *   ∂u/∂x_pd      = −Σ_f a_fd Σ_s h_fps (x_pd − c_sd)
 *   ∂u/∂c_sd      =  Σ_f a_fd Σ_p h_fps (x_pd − c_sd)
 *   ∂u/∂w_sf      =  Σ_p g_pf k_fps
 *   ∂u/∂log ℓ_fd  =  a_fd Σ_ps h_fps (x_pd − c_sd)²
 * The distances are summed as squared differences (never negative). The torch twins are
 * `qtl.policies.rbf_network._NetworkValues` (the fused op, which expands the distance) and the plain
 * autograd form of `RBFNetwork.forward`; see qtl/kernels/native/rbf_network.py.
 *
 * Layout: every operand dense and row-major: x `M x D`, c `N x D`, w `N x F`, a `F x D`, mask `M x N`
 * (or NULL), u `M x F`, k `F x M x N`, g `M x F`, and the gradients at their operands' shapes (grad_x may
 * be NULL: not wanted). The centres are transposed once per call to `D x N`, so that every inner loop runs
 * over the bases with unit stride, a vector at a time (exp through libmvec, as in pathwise.c).
 * One thread: a network of 10⁴–10⁵ (point, basis) pairs is ~0.1 ms, below what a thread team pays
 * back; the results are bit-identical run to run.
 *
 * Build: with the other sources of this directory (qtl/kernels/native/build.py).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* The vector variants exist in libmvec; glibc only announces them under -ffast-math. */
#pragma omp declare simd notinbranch
extern double exp(double);

/* c `N x D` transposed into a new `D x N` array (NULL when out of memory). */
static double *transposed(const double *c, int64_t n, int64_t dim)
{
    double *c_t = malloc((size_t)(n * dim) * sizeof(double));
    if (!c_t)
        return NULL;
    for (int64_t s = 0; s < n; ++s)
        for (int64_t d = 0; d < dim; ++d)
            c_t[d * n + s] = c[s * dim + d];
    return c_t;
}

int qtl_rbf_network_forward(const double *x, const double *c, const double *w, const double *a, const double *mask,
                            int64_t m, int64_t n, int64_t dim, int64_t f_dim, double *u, double *k)
{
    double *c_t = transposed(c, n, dim);
    double *w_t = malloc((size_t)(n * f_dim) * sizeof(double));
    if (!c_t || !w_t) {
        free(c_t);
        free(w_t);
        return 1;
    }
    for (int64_t s = 0; s < n; ++s)
        for (int64_t f = 0; f < f_dim; ++f)
            w_t[f * n + s] = w[s * f_dim + f];
    for (int64_t f = 0; f < f_dim; ++f) {
        const double *a_f = a + f * dim, *w_f = w_t + f * n;
        for (int64_t p = 0; p < m; ++p) {
            const double *x_p = x + p * dim;
            double *k_p = k + (f * m + p) * n;
            memset(k_p, 0, (size_t)n * sizeof(double));
            for (int64_t d = 0; d < dim; ++d) {
                const double x_pd = x_p[d], a_fd = a_f[d];
                const double *c_d = c_t + d * n;
#pragma omp simd
                for (int64_t s = 0; s < n; ++s) {
                    const double diff = x_pd - c_d[s];
                    k_p[s] += a_fd * diff * diff;
                }
            }
#pragma omp simd
            for (int64_t s = 0; s < n; ++s)
                k_p[s] = exp(-0.5 * k_p[s]);
            if (mask) {
                const double *m_p = mask + p * n;
#pragma omp simd
                for (int64_t s = 0; s < n; ++s)
                    k_p[s] *= m_p[s];
            }
            double total = 0.0;
#pragma omp simd reduction(+ : total)
            for (int64_t s = 0; s < n; ++s)
                total += w_f[s] * k_p[s];
            u[p * f_dim + f] = total;
        }
    }
    free(c_t);
    free(w_t);
    return 0;
}

int qtl_rbf_network_backward(const double *x, const double *c, const double *w, const double *a, const double *k,
                             const double *g, int64_t m, int64_t n, int64_t dim, int64_t f_dim, double *grad_x,
                             double *grad_c, double *grad_w, double *grad_log_ls)
{
    double *c_t = transposed(c, n, dim);
    /* per basis s: Σ_p h (x_pd − c_sd) `D x N` and Σ_p h (x_pd − c_sd)² `D x N` (per f), then h's row `N` */
    double *acc_c = calloc((size_t)(2 * dim * n + n), sizeof(double));
    if (!c_t || !acc_c) {
        free(c_t);
        free(acc_c);
        return 1;
    }
    double *acc_ls = acc_c + dim * n, *h = acc_ls + dim * n;
    if (grad_x)
        memset(grad_x, 0, (size_t)(m * dim) * sizeof(double));
    memset(grad_c, 0, (size_t)(n * dim) * sizeof(double));
    for (int64_t f = 0; f < f_dim; ++f) {
        const double *a_f = a + f * dim;
        memset(acc_c, 0, (size_t)(2 * dim * n) * sizeof(double));
        for (int64_t s = 0; s < n; ++s)
            grad_w[s * f_dim + f] = 0.0;
        for (int64_t p = 0; p < m; ++p) {
            const double g_pf = g[p * f_dim + f];
            const double *k_p = k + (f * m + p) * n, *x_p = x + p * dim;
            for (int64_t s = 0; s < n; ++s) {
                grad_w[s * f_dim + f] += g_pf * k_p[s];
                h[s] = g_pf * w[s * f_dim + f] * k_p[s];
            }
            for (int64_t d = 0; d < dim; ++d) {
                const double x_pd = x_p[d];
                const double *c_d = c_t + d * n;
                double *acc_c_d = acc_c + d * n, *acc_ls_d = acc_ls + d * n;
                double along = 0.0;
#pragma omp simd reduction(+ : along)
                for (int64_t s = 0; s < n; ++s) {
                    const double hd = h[s] * (x_pd - c_d[s]);
                    acc_c_d[s] += hd;
                    acc_ls_d[s] += hd * (x_pd - c_d[s]);
                    along += hd;
                }
                if (grad_x)
                    grad_x[p * dim + d] -= a_f[d] * along;
            }
        }
        for (int64_t d = 0; d < dim; ++d) {
            double total = 0.0;
            for (int64_t s = 0; s < n; ++s) {
                grad_c[s * dim + d] += a_f[d] * acc_c[d * n + s];
                total += acc_ls[d * n + s];
            }
            grad_log_ls[f * dim + d] = a_f[d] * total;
        }
    }
    free(c_t);
    free(acc_c);
    return 0;
}
