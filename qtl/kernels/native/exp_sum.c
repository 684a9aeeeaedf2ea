/* qtl native kernel: the fused weighted exponential sums behind PILCO's second moments.
 *
 * Maths (for each batch item b; A `n x K`, B `m x K`, W `n x m`, all float64):
 *   forward   s_b          = sum_ij W_ij exp(S_ij),      S = A B^T          (the Q sums of gp0/gp2)
 *   backward  dL/dA_ik     = g_b sum_j W_ij E_ij B_jk,   E = exp(S), g_b = dL/ds_b
 *             dL/dB_jk     = g_b sum_i W_ij E_ij A_ik
 *             dL/dW_ij     = g_b E_ij                    (written per batch item; the caller sums
 *                                                         it over W's broadcast dimensions)
 * When only A and B need gradients, the forward pass also forms, in the same pass over the tiles,
 *             G_A[i]       = sum_j W_ij E_ij B_j,   G_B[j] = sum_i W_ij E_ij A_i     (K-vectors)
 * and the backward pass is then dL/dA = g_b G_A, dL/dB = g_b G_B, without recomputing E. When W
 * needs a gradient, E is needed in backward: qtl_exp_sum_backward recomputes it, as above.
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
 * never stored. Each unit writes its own partial sum and its own partial G_B or dL/dB (one
 * buffer per unit, not per thread); partials are added in split order afterwards, so results are
 * bit-identical run after run and for any thread count.
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

/* Rows [row0, row1) of `grad_a` += sum_j s_j B_j over the chunk, and `grad_tile` (K x CHUNK_COLS,
 * transposed) += sum_i s_j A_i, for s = one row's weighted exps; either may be NULL. */
static void accumulate_row(const double *a_i, const double *s, const double *tile, int64_t cols, int64_t k,
                           double *grad_a_i, double *grad_tile)
{
    if (grad_a_i)
        for (int64_t kk = 0; kk < k; ++kk) {
            const double *t = tile + kk * CHUNK_COLS;
            double acc = 0.0;
#pragma omp simd reduction(+ : acc)
            for (int64_t jj = 0; jj < cols; ++jj)
                acc += s[jj] * t[jj];
            grad_a_i[kk] += acc;
        }
    if (grad_tile)
        for (int64_t kk = 0; kk < k; ++kk) {
            const double coef = a_i[kk];
            double *t = grad_tile + kk * CHUNK_COLS;
#pragma omp simd
            for (int64_t jj = 0; jj < cols; ++jj)
                t[jj] += coef * s[jj];
        }
}

/* grad_b[c0 + jj][kk] = grad_tile[kk][jj] for jj < cols: a chunk's transposed tile back in place. */
static void store_chunk(const double *grad_tile, int64_t cols, int64_t k, double *grad_b_chunk)
{
    for (int64_t jj = 0; jj < cols; ++jj)
        for (int64_t kk = 0; kk < k; ++kk)
            grad_b_chunk[jj * k + kk] = grad_tile[kk * CHUNK_COLS + jj];
}

/* sum over rows [row0, row1) and all m columns of W_ij exp(S_ij) for one batch item; with g_a
 * (the item's `n x k`) its rows [row0, row1) of G_A, with g_b (this unit's own `m x k`) this unit's
 * G_B, both stored, not added. The sum is formed the same way with or without them. */
static double forward_unit(const double *a, const double *b, const double *w, int64_t row0, int64_t row1,
                           int64_t m, int64_t k, double *g_a, double *g_b, double *tile, double *g_tile, double *s)
{
    if (g_a)
        memset(g_a + row0 * k, 0, (size_t)((row1 - row0) * k) * sizeof(double));
    double total = 0.0;
    for (int64_t c0 = 0; c0 < m; c0 += CHUNK_COLS) {
        const int64_t cols = min64(CHUNK_COLS, m - c0);
        transpose_chunk(b + c0 * k, cols, k, tile);
        if (g_b)
            memset(g_tile, 0, (size_t)(k * CHUNK_COLS) * sizeof(double));
        for (int64_t i = row0; i < row1; ++i) {
            row_of_s(a + i * k, tile, cols, k, s);
            const double *w_i = w + i * m + c0;
#pragma omp simd
            for (int64_t jj = 0; jj < cols; ++jj)
                s[jj] = exp(s[jj]); /* E_ij */
            double acc = 0.0;
#pragma omp simd reduction(+ : acc)
            for (int64_t jj = 0; jj < cols; ++jj)
                acc += w_i[jj] * s[jj];
            total += acc;
            if (g_a || g_b) {
#pragma omp simd
                for (int64_t jj = 0; jj < cols; ++jj)
                    s[jj] *= w_i[jj]; /* W_ij E_ij */
                accumulate_row(a + i * k, s, tile, cols, k, g_a ? g_a + i * k : NULL, g_b ? g_tile : NULL);
            }
        }
        if (g_b)
            store_chunk(g_tile, cols, k, g_b + c0 * k);
    }
    return total;
}

/* Partial dL/dB or G_B of unit (item, split): split 0 writes the item's own `m x k` rows of `dense`,
 * splits 1.. their own block of `extra` (`items x (splits - 1) x m x k`), added in split order by
 * add_split_partials, so that no two units write the same memory. */
static double *unit_partial(double *dense, double *extra, int64_t item, int64_t split, int64_t splits,
                            int64_t size)
{
    return split == 0 ? dense + item * size : extra + (item * (splits - 1) + split - 1) * size;
}

/* dense[item] += extra[item, split] for split = 1, 2, ... in that order (inside a parallel region;
 * each item by one thread, so the order of the additions is fixed). */
static void add_split_partials(double *dense, const double *extra, int64_t items, int64_t splits, int64_t size)
{
#pragma omp for schedule(static)
    for (int64_t item = 0; item < items; ++item)
        for (int64_t split = 1; split < splits; ++split) {
            const double *src = extra + (item * (splits - 1) + split - 1) * size;
            double *dst = dense + item * size;
            for (int64_t idx = 0; idx < size; ++idx)
                dst[idx] += src[idx];
        }
}

/* Scratch for the partial dL/dB or G_B of splits 1..: NULL with *failed = 0 when none is needed. */
static double *alloc_split_partials(const double *dense, int64_t items, int64_t splits, int64_t size, int *failed)
{
    *failed = 0;
    if (!dense || splits <= 1 || items <= 0 || size <= 0)
        return NULL;
    double *extra = malloc((size_t)(items * (splits - 1) * size) * sizeof(double));
    *failed = extra == NULL;
    return extra;
}

/* out `items`: the sums; g_a `items x n x k` and g_b `items x m x k`: G_A and G_B, each dense or NULL
 * when not wanted (both NULL: the plain sums). Returns 0, or 1 when scratch memory could not be
 * allocated. */
int qtl_exp_sum_forward(const double *a, const double *b, const double *w, const int64_t *off_a,
                        const int64_t *off_b, const int64_t *off_w, const int64_t *order, int64_t items,
                        int64_t n, int64_t m, int64_t k, double *out, double *g_a, double *g_b, int threads)
{
    const int64_t splits = num_splits(n);
    const int64_t units = items * splits;
    const int64_t gb_size = m * k;
    int failed = 0;
    double *extra = alloc_split_partials(g_b, items, splits, gb_size, &failed);
    double *partial = failed ? NULL : malloc((size_t)(units > 0 ? units : 1) * sizeof(double));
    if (!partial) {
        free(extra);
        return 1;
    }
    if (g_b && splits == 0)
        memset(g_b, 0, (size_t)(items * gb_size) * sizeof(double));
#pragma omp parallel num_threads(threads)
    {
        const size_t tile_size = (size_t)(k > 0 ? k : 1) * CHUNK_COLS;
        double *tile = malloc(tile_size * sizeof(double));
        double *g_tile = g_b ? malloc(tile_size * sizeof(double)) : NULL;
        double *s = malloc(CHUNK_COLS * sizeof(double));
        if (all_allocated(!tile || !s || (g_b && !g_tile), &failed)) {
#pragma omp for schedule(dynamic, 1)
            for (int64_t u = 0; u < units; ++u) {
                const int64_t item = order[u / splits], split = u % splits, row0 = split * SPLIT_ROWS;
                double *gb = g_b ? unit_partial(g_b, extra, item, split, splits, gb_size) : NULL;
                partial[item * splits + split] =
                    forward_unit(a + off_a[item], b + off_b[item], w + off_w[item], row0, min64(row0 + SPLIT_ROWS, n),
                                 m, k, g_a ? g_a + item * n * k : NULL, gb, tile, g_tile, s);
            }
            if (extra)
                add_split_partials(g_b, extra, items, splits, gb_size);
        }
        free(tile);
        free(g_tile);
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
    free(extra);
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
            memset(grad_tile, 0, (size_t)(k * CHUNK_COLS) * sizeof(double));
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
            accumulate_row(a_i, s, tile, cols, k, grad_a ? grad_a + i * k : NULL, grad_b ? grad_tile : NULL);
        }
        if (grad_b)
            store_chunk(grad_tile, cols, k, grad_b + c0 * k);
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
    int failed = 0;
    double *extra = alloc_split_partials(grad_b, items, splits, gb_size, &failed);
    if (failed)
        return 1;
    if (grad_b && splits == 0)
        memset(grad_b, 0, (size_t)(items * gb_size) * sizeof(double));
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
                double *gb = grad_b ? unit_partial(grad_b, extra, item, split, splits, gb_size) : NULL;
                backward_unit(a + off_a[item], b + off_b[item], w + off_w[item], grad_out[item], row0,
                              min64(row0 + SPLIT_ROWS, n), m, k, grad_a ? grad_a + item * n * k : NULL, gb,
                              grad_w ? grad_w + item * n * m : NULL, tile, grad_tile, s);
            }
            if (extra)
                add_split_partials(grad_b, extra, items, splits, gb_size);
        }
        free(tile);
        free(grad_tile);
        free(s);
    }
    free(extra);
    return failed;
}
