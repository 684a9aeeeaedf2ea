/* qtl native kernel: pathwise GP posterior functions (Matheron's rule) at one point per particle.
 *
 * Maths (float64). For each item b (a batch index and an output e) and each particle row p, with the
 * point z̃ = z_bp `D`, the data x̃_i `D` (i < n), the frequencies ω̃_l `D` and phases b_l (l < L), the
 * feature weights W_pl and the update v_pi, and α² the signal variance:
 *   k_i      = α² exp(−½ |z̃ − x̃_i|²)                     (the SE kernel over the lengthscales)
 *   a_l      = ω̃_lᵀ z̃ + b_l
 *   f        = Σ_l W_pl cos(a_l) + Σ_i k_i v_pi
 *   ∂f/∂z̃   = Σ_i k_i v_pi (x̃_i − z̃) − Σ_l W_pl sin(a_l) ω̃_l           (when grad is not NULL)
 * |z̃ − x̃_i|² is summed as squared differences (never negative, so no clamp is needed). The
 * plain-torch reference twin is `qtl.propagation.pathwise._PathValues` (which forms the same
 * distance as |z̃|² + |x̃|² − 2 z̃ᵀx̃, clamped); see qtl/kernels/native/pathwise.py.
 *
 * Layout: operand item b starts at element offset offsets[k * items + b] for the operands, in this
 * order, k = 0..6: z `P x D`, x `n x D`, sf2 (one value), omega `L x D`, phase `L`, w `P x L`,
 * v `P x n`; a broadcast operand repeats an offset (its copies are never materialised). Within an
 * item the rows of z, x, omega, w, v are row_strides[0..4] elements apart (0: one row broadcast over
 * the particles) and each row is contiguous. Outputs are dense: f `items x P`, grad `items x P x D`.
 *
 * Work: one unit = (item, ROWS_PER_UNIT particle rows), units in item order under OpenMP (static
 * schedule, the thread count passed per call, torch.get_num_threads()). A thread first transposes
 * its item's data to `D x n` and frequencies to `D x L` (skipped when its previous unit had the same
 * ones), so that every inner loop of a row runs over i or l with unit stride, a vector at a time:
 *   1. |z̃ − x̃_i|² for all i, one pass per input dimension; exp; times v_pi, summed;
 *   2. a_l for all l, one pass per input dimension; cos; times W_pl, summed (and with grad: sin, times W_pl);
 *   3. with grad: Σ_i k_i v_pi x̃_i and Σ_l W_pl sin(a_l) ω̃_l, one pass over i and one over l per dimension.
 * The exp, cos and sin loops run over the lengths padded to PAD (the tiles' padding is 0), so they
 * have no scalar tails.
 * Each row is computed by one thread alone: results are bit-identical for any thread count.
 *
 * Build: with the other sources of this directory (qtl/kernels/native/build.py):
 *   gcc -O3 -march=native -fno-math-errno -fopenmp -fPIC -shared -Wall -Wextra ... -lm
 * exp, sin and cos are declared `omp declare simd` below, so gcc vectorises the loops of steps 1 and 3
 * through glibc's libmvec (_ZGVeN8v_exp / _ZGVeN8v_sin / _ZGVeN8v_cos with AVX-512, the _ZGVd..4v
 * variants with AVX2) without -ffast-math; libmvec is within 4 ulp.
 */
#include <math.h>
#include <omp.h>
#include <stdint.h>
#include <stdlib.h>

#define ROWS_PER_UNIT 32 /* particle rows per work unit */
#define PAD 8            /* the transposed tiles' rows are padded to a multiple of this many doubles */
#define ALIGN 64         /* bytes: the scratch's alignment */

/* The vector variants exist in libmvec; glibc only announces them under -ffast-math. */
#pragma omp declare simd notinbranch
extern double exp(double);
#pragma omp declare simd notinbranch
extern double sin(double);
#pragma omp declare simd notinbranch
extern double cos(double);

static int64_t padded(int64_t count) { return (count + PAD - 1) / PAD * PAD; }

/* One thread's scratch: the transposed tiles, the per-row buffers and what the tiles hold now. */
struct scratch {
    double *x_t;     /* `D x np`: the item's data, transposed */
    double *omega_t; /* `D x lp`: the item's frequencies, transposed */
    double *phase;   /* `lp`: the item's phases, padded with 0 */
    double *kv;      /* `np`: k_i v_pi of the current row */
    double *angle;   /* `lp`: a_l of the current row */
    double *trig;    /* `lp`: cos(a_l), then W_pl sin(a_l) of the current row */
    int64_t x_off, omega_off, phase_off; /* the offsets the tiles were copied from (−1: none yet) */
};

/* The row-major `rows x dim` matrix at src (rows `stride` apart) transposed into dst `dim x ld`, the
 * padding columns rows..ld−1 set to 0. */
static void transpose(const double *src, int64_t rows, int64_t dim, int64_t stride, double *dst, int64_t ld)
{
    for (int64_t d = 0; d < dim; ++d) {
        for (int64_t r = 0; r < rows; ++r)
            dst[d * ld + r] = src[r * stride + d];
        for (int64_t r = rows; r < ld; ++r)
            dst[d * ld + r] = 0.0;
    }
}

/* f (returned) and, when g is not NULL, ∂f/∂z̃ into g `D`, for one particle row. */
static double row_value(const double *restrict zr, const double *restrict vr, const double *restrict wr,
                        double log_sf2, const struct scratch *sc, int64_t n,
                        int64_t np, int64_t num_features, int64_t lp, int64_t dim, double *restrict g)
{
    const double *restrict x_t = sc->x_t, *restrict omega_t = sc->omega_t;
    const double *restrict phase = sc->phase;
    double *restrict kv = sc->kv, *restrict angle = sc->angle, *restrict trig = sc->trig;
    /* 1. the data-fitted part: Σ_i k_i v_pi. |z̃ − x̃_i|² is summed in kv one input dimension at a time,
     * then exp'd, over the padded length (the tiles' padding is 0): the vector loops have no tails. */
#pragma omp simd aligned(kv : ALIGN)
    for (int64_t i = 0; i < np; ++i)
        kv[i] = 0.0;
    for (int64_t d = 0; d < dim; ++d) {
        const double *restrict xd = x_t + d * np;
        const double zd = zr[d];
#pragma omp simd aligned(xd, kv : ALIGN)
        for (int64_t i = 0; i < np; ++i) {
            const double diff = xd[i] - zd;
            kv[i] += diff * diff;
        }
    }
#pragma omp simd aligned(kv : ALIGN)
    for (int64_t i = 0; i < np; ++i)
        kv[i] = exp(log_sf2 - 0.5 * kv[i]);
    double fitted = 0.0;
#pragma omp simd reduction(+ : fitted) aligned(kv : ALIGN)
    for (int64_t i = 0; i < n; ++i) {
        kv[i] *= vr[i];
        fitted += kv[i];
    }
    /* 2. the prior part: a_l one input dimension at a time, then Σ_l W_pl cos(a_l) (and W_pl sin(a_l) kept) */
#pragma omp simd aligned(angle, phase : ALIGN)
    for (int64_t l = 0; l < lp; ++l)
        angle[l] = phase[l];
    for (int64_t d = 0; d < dim; ++d) {
        const double *restrict od = omega_t + d * lp;
        const double zd = zr[d];
#pragma omp simd aligned(od, angle : ALIGN)
        for (int64_t l = 0; l < lp; ++l)
            angle[l] += zd * od[l];
    }
#pragma omp simd aligned(angle, trig : ALIGN)
    for (int64_t l = 0; l < lp; ++l)
        trig[l] = cos(angle[l]);
    double prior = 0.0;
#pragma omp simd reduction(+ : prior) aligned(trig : ALIGN)
    for (int64_t l = 0; l < num_features; ++l)
        prior += wr[l] * trig[l];
    if (!g)
        return fitted + prior;
#pragma omp simd aligned(angle, trig : ALIGN)
    for (int64_t l = 0; l < lp; ++l)
        trig[l] = sin(angle[l]);
#pragma omp simd aligned(trig : ALIGN)
    for (int64_t l = 0; l < num_features; ++l)
        trig[l] *= wr[l];
    /* 3. ∂f/∂z̃_d = Σ_i k_i v_pi x̃_id − z̃_d Σ_i k_i v_pi − Σ_l W_pl sin(a_l) ω̃_ld */
    for (int64_t d = 0; d < dim; ++d) {
        const double *restrict xd = x_t + d * np, *restrict od = omega_t + d * lp;
        double data_part = 0.0, feature_part = 0.0;
#pragma omp simd reduction(+ : data_part) aligned(xd, kv : ALIGN)
        for (int64_t i = 0; i < n; ++i)
            data_part += kv[i] * xd[i];
#pragma omp simd reduction(+ : feature_part) aligned(od, trig : ALIGN)
        for (int64_t l = 0; l < num_features; ++l)
            feature_part += trig[l] * od[l];
        g[d] = data_part - zr[d] * fitted - feature_part;
    }
    return fitted + prior;
}

int qtl_path_values(const double *z, const double *x, const double *sf2, const double *omega, const double *phase,
                    const double *w, const double *v, const int64_t *offsets, const int64_t *row_strides,
                    int64_t items, int64_t num_rows, int64_t n, int64_t num_features, int64_t dim, double *f,
                    double *grad, int threads)
{
    const int64_t np = padded(n), lp = padded(num_features);
    const int64_t per_thread = dim * np + dim * lp + np + 3 * lp; /* multiples of PAD doubles: aligned parts */
    const int64_t units_per_item = (num_rows + ROWS_PER_UNIT - 1) / ROWS_PER_UNIT, units = items * units_per_item;
    if (threads < 1)
        threads = 1;
    if (units < threads)
        threads = units > 0 ? (int)units : 1;
    const size_t bytes = (size_t)(threads * per_thread + 1) * sizeof(double);
    double *memory = aligned_alloc(ALIGN, (bytes + ALIGN - 1) / ALIGN * ALIGN);
    if (!memory)
        return 1;
    const int64_t *off_z = offsets, *off_x = offsets + items, *off_sf2 = offsets + 2 * items,
                  *off_omega = offsets + 3 * items, *off_phase = offsets + 4 * items, *off_w = offsets + 5 * items,
                  *off_v = offsets + 6 * items;
    const int64_t z_rs = row_strides[0], x_rs = row_strides[1], omega_rs = row_strides[2], w_rs = row_strides[3],
                  v_rs = row_strides[4];
#pragma omp parallel num_threads(threads)
    {
        double *mine = memory + omp_get_thread_num() * per_thread;
        double *rows = mine + dim * (np + lp);
        struct scratch sc = {mine, mine + dim * np, rows, rows + lp, rows + lp + np, rows + 2 * lp + np, -1, -1, -1};
#pragma omp for schedule(static)
        for (int64_t unit = 0; unit < units; ++unit) {
            const int64_t b = unit / units_per_item, first = (unit % units_per_item) * ROWS_PER_UNIT;
            const int64_t last = first + ROWS_PER_UNIT < num_rows ? first + ROWS_PER_UNIT : num_rows;
            if (sc.x_off != off_x[b]) {
                transpose(x + off_x[b], n, dim, x_rs, sc.x_t, np);
                sc.x_off = off_x[b];
            }
            if (sc.omega_off != off_omega[b]) {
                transpose(omega + off_omega[b], num_features, dim, omega_rs, sc.omega_t, lp);
                sc.omega_off = off_omega[b];
            }
            if (sc.phase_off != off_phase[b]) {
                for (int64_t l = 0; l < lp; ++l)
                    sc.phase[l] = l < num_features ? phase[off_phase[b] + l] : 0.0;
                sc.phase_off = off_phase[b];
            }
            const double log_sf2 = log(sf2[off_sf2[b]]);
            for (int64_t p = first; p < last; ++p) {
                const int64_t row = b * num_rows + p;
                f[row] = row_value(z + off_z[b] + p * z_rs, v + off_v[b] + p * v_rs, w + off_w[b] + p * w_rs,
                                   log_sf2, &sc, n, np, num_features, lp, dim,
                                   grad ? grad + row * dim : NULL);
            }
        }
    }
    free(memory);
    return 0;
}
