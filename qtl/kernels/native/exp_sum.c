/* qtl native kernel: the fused weighted exponential sums behind PILCO's second moments.
 *
 * Maths (for each batch item b; A `n x K`, B `m x K`, W `n x m`, all float64):
 *   forward   s_b          = sum_ij W_ij exp(S_ij),      S = A B^T          (the Q sums of gp0/gp2)
 *   backward  dL/dA_ik     = g_b sum_j W_ij E_ij B_jk,   E = exp(S), g_b = dL/ds_b
 *             dL/dB_jk     = g_b sum_i W_ij E_ij A_ik
 *             dL/dW_ij     = g_b E_ij                    (written per batch item; the caller sums
 *                                                         it over W's broadcast dimensions)
 * The plain-torch reference twin is `qtl.kernels.exp_sum._WeightedExpSum`.
 *
 * Layout: every matrix is row-major and contiguous in its last two dimensions; batch item b of
 * A, B, W starts at element offset off_a[b], off_b[b], off_w[b] (a broadcast W repeats an offset,
 * so its copies are never materialised). Outputs are dense over the batch.
 *
 * Work: one unit = (batch item, SPLIT_ROWS rows of A); units run in parallel under OpenMP with
 * the thread count passed per call (torch.get_num_threads()), items in the order `order` (the
 * caller groups the items that share a W, so that a broadcast W is read while still in cache). Inside a unit, B is taken in
 * chunks of CHUNK_COLS rows, transposed once into a K x CHUNK_COLS tile (L1/L2-resident), and
 * each row of A forms S_i,chunk, exp, weight and sum in one pass over that tile: exp(A B^T) is
 * never stored. Each unit writes its own partial sum (forward) or partial dL/dB (backward);
 * partials are added in a fixed order afterwards, so results do not depend on the thread count.
 *
 * Build (qtl/kernels/native/build.py, `python -m qtl.kernels.native.build`, run by
 * scripts/setup.sh; cached by a hash of this file, the flags and the CPU):
 *   gcc -O3 -march=native -fno-math-errno -fopenmp -fPIC -shared -Wall -Wextra exp_sum.c -lm
 * exp is declared `omp declare simd` below, so gcc vectorises the exp loops through glibc's
 * libmvec (_ZGVeN8v_exp with AVX-512, _ZGVdN4v_exp with AVX2) without -ffast-math; libmvec's
 * exp is within 4 ulp, and the sums agree with the torch twin to ~1e-15 relative (see
 * tests/kernels/test_exp_sum.py). Loaded through ctypes after torch, so it shares torch's libgomp.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define SPLIT_ROWS 256
#define CHUNK_COLS 512

/* The vector variants of exp exist in libmvec; glibc only announces them under -ffast-math. */
#pragma omp declare simd notinbranch
extern double exp(double);

static int64_t num_splits(int64_t n) { return (n + SPLIT_ROWS - 1) / SPLIT_ROWS; }

static int64_t min64(int64_t x, int64_t y) { return x < y ? x : y; }

/* Inside a parallel region: whether every thread got its scratch memory (a barrier, so that all
 * threads take the same branch around the work-sharing loops that follow). */
static int all_allocated(int mine_failed, int *failed)
{
    if (mine_failed) {
#pragma omp atomic write
        *failed = 1;
    }
#pragma omp barrier
    int any_failed;
#pragma omp atomic read
    any_failed = *failed;
    return !any_failed;
}

/* tile[kk * CHUNK_COLS + jj] = b[jj * k + kk] for jj < cols. */
static void transpose_chunk(const double *b, int64_t cols, int64_t k, double *tile)
{
    for (int64_t jj = 0; jj < cols; ++jj)
        for (int64_t kk = 0; kk < k; ++kk)
            tile[kk * CHUNK_COLS + jj] = b[jj * k + kk];
}

/* s[jj] = sum_kk a_i[kk] tile[kk][jj]: one row of S over the chunk. */
static void row_of_s(const double *a_i, const double *tile, int64_t cols, int64_t k, double *s)
{
    for (int64_t jj = 0; jj < cols; ++jj)
        s[jj] = 0.0;
    for (int64_t kk = 0; kk < k; ++kk) {
        const double coef = a_i[kk];
        const double *t = tile + kk * CHUNK_COLS;
#pragma omp simd
        for (int64_t jj = 0; jj < cols; ++jj)
            s[jj] += coef * t[jj];
    }
}

/* sum over rows [row0, row1) and all m columns of W_ij exp(S_ij) for one batch item. */
static double forward_unit(const double *a, const double *b, const double *w, int64_t row0, int64_t row1,
                           int64_t m, int64_t k, double *tile, double *s)
{
    double total = 0.0;
    for (int64_t c0 = 0; c0 < m; c0 += CHUNK_COLS) {
        const int64_t cols = min64(CHUNK_COLS, m - c0);
        transpose_chunk(b + c0 * k, cols, k, tile);
        for (int64_t i = row0; i < row1; ++i) {
            row_of_s(a + i * k, tile, cols, k, s);
            const double *w_i = w + i * m + c0;
            double acc = 0.0;
#pragma omp simd reduction(+ : acc)
            for (int64_t jj = 0; jj < cols; ++jj)
                acc += w_i[jj] * exp(s[jj]);
            total += acc;
        }
    }
    return total;
}

/* Returns 0, or 1 when scratch memory could not be allocated. */
int qtl_exp_sum_forward(const double *a, const double *b, const double *w, const int64_t *off_a,
                        const int64_t *off_b, const int64_t *off_w, const int64_t *order, int64_t items,
                        int64_t n, int64_t m, int64_t k, double *out, int threads)
{
    const int64_t splits = num_splits(n);
    const int64_t units = items * splits;
    double *partial = malloc((size_t)(units > 0 ? units : 1) * sizeof(double));
    if (!partial)
        return 1;
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        double *tile = malloc((size_t)(k > 0 ? k : 1) * CHUNK_COLS * sizeof(double));
        double *s = malloc(CHUNK_COLS * sizeof(double));
        if (all_allocated(!tile || !s, &failed)) {
#pragma omp for schedule(dynamic, 1)
            for (int64_t u = 0; u < units; ++u) {
                const int64_t item = order[u / splits], split = u % splits, row0 = split * SPLIT_ROWS;
                partial[item * splits + split] = forward_unit(a + off_a[item], b + off_b[item], w + off_w[item], row0,
                                          min64(row0 + SPLIT_ROWS, n), m, k, tile, s);
            }
        }
        free(tile);
        free(s);
    }
    if (!failed)
        for (int64_t item = 0; item < items; ++item) {
            double total = 0.0;
            for (int64_t sp = 0; sp < splits; ++sp)
                total += partial[item * splits + sp];
            out[item] = total;
        }
    free(partial);
    return failed;
}

/* Gradients of one unit: rows [row0, row1) of dL/dA and dL/dW, and this unit's dL/dB (all m rows,
 * stored, not added, into grad_b). Null outputs are not wanted. */
static void backward_unit(const double *a, const double *b, const double *w, double g, int64_t row0,
                          int64_t row1, int64_t m, int64_t k, double *grad_a, double *grad_b, double *grad_w,
                          double *tile, double *grad_tile, double *s)
{
    if (grad_a)
        memset(grad_a + row0 * k, 0, (size_t)((row1 - row0) * k) * sizeof(double));
    for (int64_t c0 = 0; c0 < m; c0 += CHUNK_COLS) {
        const int64_t cols = min64(CHUNK_COLS, m - c0);
        transpose_chunk(b + c0 * k, cols, k, tile);
        if (grad_b)
            for (int64_t idx = 0; idx < k * CHUNK_COLS; ++idx)
                grad_tile[idx] = 0.0;
        for (int64_t i = row0; i < row1; ++i) {
            const double *a_i = a + i * k;
            const double *w_i = w + i * m + c0;
            row_of_s(a_i, tile, cols, k, s);
#pragma omp simd
            for (int64_t jj = 0; jj < cols; ++jj)
                s[jj] = g * exp(s[jj]); /* g E_ij */
            if (grad_w)
                memcpy(grad_w + i * m + c0, s, (size_t)cols * sizeof(double));
#pragma omp simd
            for (int64_t jj = 0; jj < cols; ++jj)
                s[jj] *= w_i[jj]; /* g W_ij E_ij */
            if (grad_a)
                for (int64_t kk = 0; kk < k; ++kk) {
                    const double *t = tile + kk * CHUNK_COLS;
                    double acc = 0.0;
#pragma omp simd reduction(+ : acc)
                    for (int64_t jj = 0; jj < cols; ++jj)
                        acc += s[jj] * t[jj];
                    grad_a[i * k + kk] += acc;
                }
            if (grad_b)
                for (int64_t kk = 0; kk < k; ++kk) {
                    const double coef = a_i[kk];
                    double *t = grad_tile + kk * CHUNK_COLS;
#pragma omp simd
                    for (int64_t jj = 0; jj < cols; ++jj)
                        t[jj] += coef * s[jj];
                }
        }
        if (grad_b)
            for (int64_t jj = 0; jj < cols; ++jj)
                for (int64_t kk = 0; kk < k; ++kk)
                    grad_b[(c0 + jj) * k + kk] = grad_tile[kk * CHUNK_COLS + jj];
    }
}

/* grad_out `items`; grad_a `items x n x k`, grad_b `items x m x k`, grad_w `items x n x m`, each
 * dense or NULL when not wanted. Returns 0, or 1 when scratch memory could not be allocated. */
int qtl_exp_sum_backward(const double *a, const double *b, const double *w, const int64_t *off_a,
                         const int64_t *off_b, const int64_t *off_w, const int64_t *order, int64_t items,
                         int64_t n, int64_t m, int64_t k, const double *grad_out, double *grad_a,
                         double *grad_b, double *grad_w, int threads)
{
    const int64_t splits = num_splits(n);
    const int64_t units = items * splits;
    const int64_t gb_size = m * k;
    /* dL/dB of split 0 goes straight to grad_b; splits 1.. to scratch, added in order below. */
    double *extra = NULL;
    if (grad_b && splits > 1 && items > 0 && gb_size > 0) {
        extra = malloc((size_t)(items * (splits - 1) * gb_size) * sizeof(double));
        if (!extra)
            return 1;
    }
    if (grad_b && splits == 0)
        memset(grad_b, 0, (size_t)(items * gb_size) * sizeof(double));
    int failed = 0;
#pragma omp parallel num_threads(threads)
    {
        const size_t tile_size = (size_t)(k > 0 ? k : 1) * CHUNK_COLS;
        double *tile = malloc(tile_size * sizeof(double));
        double *grad_tile = grad_b ? malloc(tile_size * sizeof(double)) : NULL;
        double *s = malloc(CHUNK_COLS * sizeof(double));
        if (all_allocated(!tile || !s || (grad_b && !grad_tile), &failed)) {
#pragma omp for schedule(dynamic, 1)
            for (int64_t u = 0; u < units; ++u) {
                const int64_t item = order[u / splits], split = u % splits, row0 = split * SPLIT_ROWS;
                double *gb = NULL;
                if (grad_b)
                    gb = split == 0 ? grad_b + item * gb_size
                                    : extra + (item * (splits - 1) + split - 1) * gb_size;
                backward_unit(a + off_a[item], b + off_b[item], w + off_w[item], grad_out[item], row0,
                              min64(row0 + SPLIT_ROWS, n), m, k, grad_a ? grad_a + item * n * k : NULL, gb,
                              grad_w ? grad_w + item * n * m : NULL, tile, grad_tile, s);
            }
            if (extra) {
#pragma omp for schedule(static)
                for (int64_t item = 0; item < items; ++item)
                    for (int64_t split = 1; split < splits; ++split) {
                        const double *src = extra + (item * (splits - 1) + split - 1) * gb_size;
                        double *dst = grad_b + item * gb_size;
                        for (int64_t idx = 0; idx < gb_size; ++idx)
                            dst[idx] += src[idx];
                    }
            }
        }
        free(tile);
        free(grad_tile);
        free(s);
    }
    free(extra);
    return failed;
}
