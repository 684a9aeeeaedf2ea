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
 * Lower items, forward only (qtl_exp_sum_forward_lower; n = m): when S is symmetric (any W),
 *             s_b          = sum_{j<i} (W_ij + W_ji) E_ij + sum_i W_ii E_ii
 * is the same sum from the lower triangle, about half the entries. G_A and G_B are then the gradients
 * of this lower form (P_ij = (W_ij + W_ji) E_ij below the diagonal, W_ii E_ii on it, 0 above): not the
 * full G_A and G_B, but wherever A(θ) and B(θ) keep S symmetric for every θ the chain rule through
 * both gives the same dL/dθ, so a caller that builds A and B so (the a = b pairs of se_moments.c) may
 * use them; dL/dW (qtl_exp_sum_backward) is the full form's, E_ij, equal to the lower form's then.
 * The plain-torch reference twin is `qtl.kernels.exp_sum._WeightedExpSum`.
 *
 * Layout: every matrix is row-major and contiguous in its last two dimensions; batch item b of
 * A, B, W starts at element offset off_a[b], off_b[b], off_w[b] (a broadcast W repeats an offset,
 * so its copies are never materialised). Outputs are dense over the batch.
 *
 * Work: one unit = (batch item, SPLIT_ROWS rows of A); units run in parallel under OpenMP with
 * the thread count passed per call (torch.get_num_threads()), items in the order `order` (the
 * caller groups the items that share a W, so that a broadcast W is read while still in cache).
 * Inside a unit, B is taken in chunks of CHUNK_COLS rows, copied once into two L1/L2-resident
 * tiles: transposed (`K x CHUNK_COLS`, columns padded with zeros to a multiple of LANES) and row by
 * row with each row's K padded with zeros to a multiple of LANES. A is taken BLOCK_ROWS rows at a
 * time (a short last block padded with zero rows; the next block's W rows are prefetched), and each
 * (row block, chunk) goes in four steps:
 *   1. S for BLOCK_ROWS rows x LANES columns at a time, in registers (the columns are the vector
 *      lanes, the rows BLOCK_ROWS accumulators, the transposed tile's columns loaded once per k);
 *   2. exp over the block's S, one contiguous loop through libmvec's 8-wide exp;
 *   3. times W (and the backward's g), summed; dL/dW written; padded rows set to 0;
 *   4. G_A and G_B, column by column: G_A[i] += P_ij B_j for the block's rows (BLOCK_ROWS
 *      accumulators of LANES k's in registers) and G_B[j] += sum_i P_ij A_i (one register), with
 *      P = W E; K > LANES takes one such pass per LANES k's.
 * exp(A B^T) is never stored beyond one block. Each unit writes its own partial sum and its own
 * partial G_B or dL/dB (one buffer per unit, not per thread); partials are added in split order
 * afterwards, so results are bit-identical run after run and for any thread count.
 *
 * Build (qtl/kernels/native/build.py, `python -m qtl.kernels.native.build`, run by
 * scripts/setup.sh; cached by a hash of this file, the flags and the CPU):
 *   gcc -O3 -march=native -fno-math-errno -fopenmp -fPIC -shared -Wall -Wextra exp_sum.c -lm
 * The register tiles are GNU C vectors of LANES doubles, one register of the CPU compiled for (8
 * with AVX-512, 4 with AVX, 2 otherwise). exp is declared `omp declare simd` below, so gcc
 * vectorises the exp loop, LANES at a time, through glibc's libmvec (_ZGVeN8v_exp, _ZGVdN4v_exp,
 * _ZGVbN2v_exp) without -ffast-math; libmvec's exp is within 4 ulp, and the sums agree with the
 * torch twin to ~1e-15 relative (see tests/kernels/test_exp_sum.py). Loaded through ctypes after
 * torch, so it shares torch's libgomp.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define SPLIT_ROWS 256 /* rows of A per work unit (a multiple of BLOCK_ROWS) */
#define CHUNK_COLS 128 /* rows of B per tile (a multiple of LANES; the tiles then fit L1) */
/* LANES: doubles per vector register; BLOCK_ROWS: rows of A per register block (block_grads keeps
 * 2 BLOCK_ROWS + 2 vectors live: 18 of AVX-512's 32 registers, 10 of AVX's 16). */
#if defined(__AVX512F__)
#define LANES 8
#define BLOCK_ROWS 8
#elif defined(__AVX__)
#define LANES 4
#define BLOCK_ROWS 4
#else
#define LANES 2
#define BLOCK_ROWS 4
#endif
#define ALIGN 64 /* bytes: the tiles' alignment (at least a vector's) */

/* Before a loop over a block's rows: unrolled, so that its vectors stay in registers. */
#define FULLY_UNROLLED _Pragma("GCC unroll 16")
_Static_assert(BLOCK_ROWS <= 16, "FULLY_UNROLLED unrolls up to 16 rows");
_Static_assert(SPLIT_ROWS % BLOCK_ROWS == 0 && CHUNK_COLS % LANES == 0, "blocks tile units, lanes tile chunks");
_Static_assert(ALIGN % (LANES * sizeof(double)) == 0, "the tiles are aligned for vector loads");

typedef double vec __attribute__((vector_size(LANES * sizeof(double))));

/* The vector variants of exp exist in libmvec; glibc only announces them under -ffast-math. */
#pragma omp declare simd notinbranch
extern double exp(double);

static int64_t num_splits(int64_t n) { return (n + SPLIT_ROWS - 1) / SPLIT_ROWS; }

static int64_t min64(int64_t x, int64_t y) { return x < y ? x : y; }

static int64_t round_up(int64_t x) { return (x + LANES - 1) / LANES * LANES; }

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

/* One thread's tiles (ALIGN-aligned); kp = K rounded up to LANES. */
struct scratch {
    int64_t kp;
    double *b_t;   /* `K x CHUNK_COLS`: the chunk of B transposed, padded columns 0 */
    double *b_row; /* `CHUNK_COLS x kp`: the chunk of B, each row's K padded with 0 */
    double *g_b;   /* `CHUNK_COLS x kp`: the chunk's G_B, summed over the unit's rows */
    double *a_row; /* `BLOCK_ROWS x kp`: the block of A, padded rows and K 0 */
    double *g_a;   /* `BLOCK_ROWS x kp`: the block's G_A over the chunk */
    double *e;     /* `BLOCK_ROWS x cols`: S, then E, then P = W E (cols = the chunk's padded width) */
    double *w_t;   /* `BLOCK_ROWS x CHUNK_COLS`: a lower item's W_ji for the block's rows i, chunk's j */
};

static double *alloc_aligned(int64_t count)
{
    const size_t bytes = (size_t)(count > 0 ? count : 1) * sizeof(double);
    return aligned_alloc(ALIGN, (bytes + ALIGN - 1) / ALIGN * ALIGN);
}

/* Allocates a thread's tiles for K = k; returns 0, or 1 when memory is short (then free_scratch). */
static int alloc_scratch(struct scratch *sc, int64_t k)
{
    sc->kp = round_up(k > 0 ? k : 1);
    sc->b_t = alloc_aligned(k * CHUNK_COLS);
    sc->b_row = alloc_aligned(CHUNK_COLS * sc->kp);
    sc->g_b = alloc_aligned(CHUNK_COLS * sc->kp);
    sc->a_row = alloc_aligned(BLOCK_ROWS * sc->kp);
    sc->g_a = alloc_aligned(BLOCK_ROWS * sc->kp);
    sc->e = alloc_aligned(BLOCK_ROWS * CHUNK_COLS);
    sc->w_t = alloc_aligned(BLOCK_ROWS * CHUNK_COLS);
    return !sc->b_t || !sc->b_row || !sc->g_b || !sc->a_row || !sc->g_a || !sc->e || !sc->w_t;
}

static void free_scratch(struct scratch *sc)
{
    free(sc->b_t);
    free(sc->b_row);
    free(sc->g_b);
    free(sc->a_row);
    free(sc->g_a);
    free(sc->e);
    free(sc->w_t);
}

/* The tiles of B's rows [0, cols) (b: the chunk's first row): b_t and b_row, zero-padded. */
static void load_chunk(const double *b, int64_t cols, int64_t k, struct scratch *sc)
{
    const int64_t cols_p = round_up(cols), kp = sc->kp;
    memset(sc->b_row, 0, (size_t)(cols_p * kp) * sizeof(double));
    for (int64_t jj = 0; jj < cols; ++jj)
        memcpy(sc->b_row + jj * kp, b + jj * k, (size_t)k * sizeof(double));
    for (int64_t kk = 0; kk < k; ++kk) {
        double *t = sc->b_t + kk * CHUNK_COLS;
        for (int64_t jj = 0; jj < cols; ++jj)
            t[jj] = b[jj * k + kk];
        for (int64_t jj = cols; jj < cols_p; ++jj)
            t[jj] = 0.0;
    }
}

/* a_row = A's rows [0, rows) (a: the block's first row), then zero rows up to BLOCK_ROWS. */
static void load_block(const double *a, int64_t rows, int64_t k, struct scratch *sc)
{
    memset(sc->a_row, 0, (size_t)(BLOCK_ROWS * sc->kp) * sizeof(double));
    for (int64_t r = 0; r < rows; ++r)
        memcpy(sc->a_row + r * sc->kp, a + r * k, (size_t)k * sizeof(double));
}

/* Asks for `rows` rows of W's `cols` columns from w on (the next block's) to be read into cache. */
static void prefetch_rows(const double *w, int64_t rows, int64_t m, int64_t cols)
{
    for (int64_t r = 0; r < rows; ++r)
        for (int64_t jj = 0; jj < cols; jj += ALIGN / sizeof(double))
            __builtin_prefetch(w + r * m + jj, 0, 0);
}

/* Step 1: e[r][jj] = S = sum_k a_row[r][k] b_t[k][jj] for the block's rows and jj < cols_p. */
static void block_of_s(const struct scratch *sc, int64_t k, int64_t cols_p)
{
    for (int64_t jj = 0; jj < cols_p; jj += LANES) {
        vec acc[BLOCK_ROWS] = {0};
        for (int64_t kk = 0; kk < k; ++kk) {
            const vec t = *(const vec *)(sc->b_t + kk * CHUNK_COLS + jj);
            FULLY_UNROLLED
            for (int r = 0; r < BLOCK_ROWS; ++r)
                acc[r] += sc->a_row[r * sc->kp + kk] * t;
        }
        FULLY_UNROLLED
        for (int r = 0; r < BLOCK_ROWS; ++r)
            *(vec *)(sc->e + r * cols_p + jj) = acc[r];
    }
}

/* Step 2: e = exp(e) over `count` entries (a multiple of LANES), LANES at a time through libmvec. */
static void exp_in_place(double *e, int64_t count)
{
#pragma omp simd simdlen(LANES) aligned(e : ALIGN)
    for (int64_t idx = 0; idx < count; ++idx)
        e[idx] = exp(e[idx]); /* E_ij */
}

/* Step 3 for one row: e = g E (stored into grad_w when wanted), then P = W g E; returns sum_j P. */
static double weigh_row(double *e, const double *w, double g, int64_t cols, double *grad_w)
{
    double acc = 0.0;
#pragma omp simd reduction(+ : acc)
    for (int64_t jj = 0; jj < cols; ++jj) {
        e[jj] *= g; /* g E_ij (g = 1 in the forward: exact) */
        acc += w[jj] * e[jj];
    }
    if (grad_w)
        memcpy(grad_w, e, (size_t)cols * sizeof(double));
#pragma omp simd
    for (int64_t jj = 0; jj < cols; ++jj)
        e[jj] *= w[jj]; /* P_ij = g W_ij E_ij */
    return acc;
}

/* w_t[r][jj] = W_ji for the block's rows i = r0 + r (r < rows) and the chunk's columns j = c0 + jj < c0 + cols
 * (w: W's row c0 from its column r0 on; each j reads `rows` contiguous doubles). */
static void load_w_transposed(const double *w, int64_t rows, int64_t cols, int64_t m, struct scratch *sc)
{
    for (int64_t jj = 0; jj < cols; ++jj)
        for (int64_t r = 0; r < rows; ++r)
            sc->w_t[r * CHUNK_COLS + jj] = w[jj * m + r];
}

/* Step 3 for one row i of a lower item (no dL/dW): P_ij = g (W_ij + W_ji) E_ij left of the row's diagonal
 * column `diag` (an index into the chunk; it may lie outside it), g W_ii E_ii on it and 0 right of it;
 * w: the row's W_ij, w_t: its W_ji. Returns sum_j P. */
static double weigh_row_lower(double *e, const double *w, const double *w_t, double g, int64_t cols, int64_t diag)
{
    const int64_t below = diag < 0 ? 0 : min64(diag, cols);
    double acc = 0.0;
#pragma omp simd reduction(+ : acc)
    for (int64_t jj = 0; jj < below; ++jj) {
        e[jj] = g * (w[jj] + w_t[jj]) * e[jj];
        acc += e[jj];
    }
    if (diag >= 0 && diag < cols) {
        e[diag] = g * w[diag] * e[diag];
        acc += e[diag];
    }
    for (int64_t jj = (diag < 0 ? 0 : diag + 1); jj < cols; ++jj)
        e[jj] = 0.0; /* above the diagonal: counted by its mirror image */
    return acc;
}

/* Step 4 for the k's [v, v + LANES): g_a[r] = sum_jj P[r][jj] B_jj and g_b[jj] += sum_r P[r][jj] A_r. */
static void block_grads(struct scratch *sc, int64_t v, int64_t cols, int64_t cols_p)
{
    const int64_t kp = sc->kp;
    vec a[BLOCK_ROWS], g_a[BLOCK_ROWS] = {0};
    FULLY_UNROLLED
    for (int r = 0; r < BLOCK_ROWS; ++r)
        a[r] = *(const vec *)(sc->a_row + r * kp + v);
    for (int64_t jj = 0; jj < cols; ++jj) {
        const vec b = *(const vec *)(sc->b_row + jj * kp + v);
        vec *g_b = (vec *)(sc->g_b + jj * kp + v);
        vec sum = *g_b;
        FULLY_UNROLLED
        for (int r = 0; r < BLOCK_ROWS; ++r) {
            const double p = sc->e[r * cols_p + jj];
            g_a[r] += p * b;
            sum += p * a[r];
        }
        *g_b = sum;
    }
    FULLY_UNROLLED
    for (int r = 0; r < BLOCK_ROWS; ++r)
        *(vec *)(sc->g_a + r * kp + v) = g_a[r];
}

/* One batch item's operands and the outputs a unit writes (each NULL when not wanted). */
struct unit {
    const double *a, *b, *w; /* the item's A `n x k`, B `m x k`, W `n x m` */
    int64_t m, k;
    int lower;               /* the lower form (S symmetric, n = m; forward only: see the top of this file) */
    double g;                /* the scale of E: dL/ds in the backward, 1 in the forward */
    double *g_a;             /* the item's `n x k`: G_A (or dL/dA), rows of this unit stored */
    double *g_b;             /* this unit's own `m x k`: its G_B (or dL/dB), stored */
    double *g_w;             /* the item's `n x m`: dL/dW, rows of this unit stored */
};

/* sum over rows [row0, row1) and all m columns of W_ij g exp(S_ij) for one unit, with its rows of
 * g_a and its g_b, g_w where wanted (a lower unit: the lower form, columns up to each row block's
 * last diagonal only). The sum is formed the same way whatever is wanted. */
static double run_unit(const struct unit *u, int64_t row0, int64_t row1, struct scratch *sc)
{
    const int64_t m = u->m, k = u->k, kp = sc->kp;
    const int grads = u->g_a || u->g_b;
    if (u->g_a)
        memset(u->g_a + row0 * k, 0, (size_t)((row1 - row0) * k) * sizeof(double));
    double total = 0.0;
    for (int64_t c0 = 0; c0 < m; c0 += CHUNK_COLS) {
        const int64_t cols = min64(CHUNK_COLS, m - c0), cols_p = round_up(cols);
        load_chunk(u->b + c0 * k, cols, k, sc);
        if (grads)
            memset(sc->g_b, 0, (size_t)(cols_p * kp) * sizeof(double));
        for (int64_t r0 = row0; r0 < row1; r0 += BLOCK_ROWS) {
            const int64_t rows = min64(BLOCK_ROWS, row1 - r0);
            /* the block's columns: all of the chunk's, or (lower) those up to its last row's diagonal */
            const int64_t used = u->lower ? min64(cols, r0 + rows - c0) : cols, used_p = round_up(used);
            if (used <= 0)
                continue; /* the chunk lies above the diagonal of every row of the block */
            load_block(u->a + r0 * k, rows, k, sc);
            if (r0 + BLOCK_ROWS < row1)
                prefetch_rows(u->w + (r0 + BLOCK_ROWS) * m + c0, min64(BLOCK_ROWS, row1 - r0 - BLOCK_ROWS), m, used);
            block_of_s(sc, k, used_p);
            exp_in_place(sc->e, rows * used_p);
            if (u->lower)
                load_w_transposed(u->w + c0 * m + r0, rows, used, m, sc);
            for (int64_t r = 0; r < rows; ++r) {
                double *e = sc->e + r * used_p;
                const double *w = u->w + (r0 + r) * m + c0;
                total += u->lower ? weigh_row_lower(e, w, sc->w_t + r * CHUNK_COLS, u->g, used, r0 + r - c0)
                                  : weigh_row(e, w, u->g, used, u->g_w ? u->g_w + (r0 + r) * m + c0 : NULL);
            }
            /* padded rows: P = 0 (step 4 reads only the block's used columns) */
            memset(sc->e + rows * used_p, 0, (size_t)((BLOCK_ROWS - rows) * used_p) * sizeof(double));
            if (!grads)
                continue;
            for (int64_t v = 0; v < kp; v += LANES)
                block_grads(sc, v, used, used_p);
            if (u->g_a)
                for (int64_t r = 0; r < rows; ++r)
                    for (int64_t kk = 0; kk < k; ++kk)
                        u->g_a[(r0 + r) * k + kk] += sc->g_a[r * kp + kk];
        }
        if (u->g_b)
            for (int64_t jj = 0; jj < cols; ++jj)
                memcpy(u->g_b + (c0 + jj) * k, sc->g_b + jj * kp, (size_t)k * sizeof(double));
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

/* Every unit of every item in parallel: partial[item * splits + split] its sum; g_a `items x n x k`,
 * g_b `items x m x k` (the split partials added), g_w `items x n x m`, each dense or NULL; lower `items`:
 * a flag per item, the lower form (NULL: none); scale `items` (NULL: 1). Returns 0, or 1 when scratch
 * memory could not be allocated. */
static int run_units(const double *a, const double *b, const double *w, const int64_t *off_a,
                     const int64_t *off_b, const int64_t *off_w, const int64_t *order, int64_t items, int64_t n,
                     int64_t m, int64_t k, const unsigned char *lower, const double *scale, double *partial,
                     double *g_a, double *g_b, double *g_w, int threads)
{
    const int64_t splits = num_splits(n);
    const int64_t units = items * splits;
    const int64_t gb_size = m * k;
    int failed = 0;
    double *extra = alloc_split_partials(g_b, items, splits, gb_size, &failed);
    if (failed)
        return 1;
    if (g_b && splits == 0)
        memset(g_b, 0, (size_t)(items * gb_size) * sizeof(double));
#pragma omp parallel num_threads(threads)
    {
        struct scratch sc;
        if (all_allocated(alloc_scratch(&sc, k), &failed)) {
#pragma omp for schedule(dynamic, 1)
            for (int64_t u = 0; u < units; ++u) {
                const int64_t item = order[u / splits], split = u % splits, row0 = split * SPLIT_ROWS;
                const struct unit job = {
                    .a = a + off_a[item],
                    .b = b + off_b[item],
                    .w = w + off_w[item],
                    .m = m,
                    .k = k,
                    .lower = lower ? lower[item] != 0 : 0,
                    .g = scale ? scale[item] : 1.0,
                    .g_a = g_a ? g_a + item * n * k : NULL,
                    .g_b = g_b ? unit_partial(g_b, extra, item, split, splits, gb_size) : NULL,
                    .g_w = g_w ? g_w + item * n * m : NULL,
                };
                partial[item * splits + split] = run_unit(&job, row0, min64(row0 + SPLIT_ROWS, n), &sc);
            }
            if (extra)
                add_split_partials(g_b, extra, items, splits, gb_size);
        }
        free_scratch(&sc);
    }
    free(extra);
    return failed;
}

/* The forward pass of qtl_exp_sum_forward and qtl_exp_sum_forward_lower (lower: NULL, or a flag per item). */
static int forward(const double *a, const double *b, const double *w, const int64_t *off_a, const int64_t *off_b,
                   const int64_t *off_w, const int64_t *order, int64_t items, int64_t n, int64_t m, int64_t k,
                   const unsigned char *lower, double *out, double *g_a, double *g_b, int threads)
{
    const int64_t splits = num_splits(n);
    double *partial = malloc((size_t)(items * splits > 0 ? items * splits : 1) * sizeof(double));
    if (!partial)
        return 1;
    const int failed = run_units(a, b, w, off_a, off_b, off_w, order, items, n, m, k, lower, NULL, partial, g_a,
                                 g_b, NULL, threads);
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

/* out `items`: the sums; g_a `items x n x k` and g_b `items x m x k`: G_A and G_B, each dense or NULL
 * when not wanted (both NULL: the plain sums). Returns 0, or 1 when scratch memory could not be
 * allocated. */
int qtl_exp_sum_forward(const double *a, const double *b, const double *w, const int64_t *off_a,
                        const int64_t *off_b, const int64_t *off_w, const int64_t *order, int64_t items,
                        int64_t n, int64_t m, int64_t k, double *out, double *g_a, double *g_b, int threads)
{
    return forward(a, b, w, off_a, off_b, off_w, order, items, n, m, k, NULL, out, g_a, g_b, threads);
}

/* As qtl_exp_sum_forward, with the items whose flag in lower `items` is nonzero summed in the lower
 * form (S symmetric: see the top of this file; their G_A and G_B are the lower form's). Returns
 * 0, 1 when scratch memory could not be allocated, or 2 when an item is lower but n != m. */
int qtl_exp_sum_forward_lower(const double *a, const double *b, const double *w, const int64_t *off_a,
                              const int64_t *off_b, const int64_t *off_w, const int64_t *order, int64_t items,
                              int64_t n, int64_t m, int64_t k, const unsigned char *lower, double *out,
                              double *g_a, double *g_b, int threads)
{
    for (int64_t item = 0; item < items && n != m; ++item)
        if (lower[item])
            return 2;
    return forward(a, b, w, off_a, off_b, off_w, order, items, n, m, k, lower, out, g_a, g_b, threads);
}

/* grad_out `items`; grad_a `items x n x k`, grad_b `items x m x k`, grad_w `items x n x m`, each
 * dense or NULL when not wanted. Returns 0, or 1 when scratch memory could not be allocated. */
int qtl_exp_sum_backward(const double *a, const double *b, const double *w, const int64_t *off_a,
                         const int64_t *off_b, const int64_t *off_w, const int64_t *order, int64_t items,
                         int64_t n, int64_t m, int64_t k, const double *grad_out, double *grad_a,
                         double *grad_b, double *grad_w, int threads)
{
    const int64_t splits = num_splits(n);
    double *partial = malloc((size_t)(items * splits > 0 ? items * splits : 1) * sizeof(double));
    if (!partial)
        return 1;
    const int failed = run_units(a, b, w, off_a, off_b, off_w, order, items, n, m, k, NULL, grad_out, partial,
                                 grad_a, grad_b, grad_w, threads);
    free(partial);
    return failed;
}
