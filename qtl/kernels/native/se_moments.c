/* qtl native kernel: the moments of SE-kernel regressors at Gaussian inputs (PILCO gp0/gp2), fused.
 *
 * Maths (per batch item; c_a = 1/ℓ_a the inverse lengthscales `E x D`, x_i the inputs `n x D`,
 * β `E x n`, log α_a², W_p `n x n` per unordered output pair p = (a <= b) in triu order, and the
 * Gaussian input N(μ, Σ); the plain-torch twin is `SEKernelMoments._fused_call` in
 * qtl/kernels/moments.py, and every line below follows it):
 *   ν_i = x_i − μ
 *   B_a = (c_a c_aᵀ) ∘ Σ + I,  h_a = ½ log|B_a|          (Cholesky; B_a⁻¹ = L⁻ᵀL⁻¹, exactly symmetric)
 *   q_ai = exp(log α_a² − h_a − ½ (ν_i∘c_a)ᵀ B_a⁻¹ (ν_i∘c_a)),  mean_a = Σ_i β_ai q_ai
 *   gain[:, a] = c_a ∘ Σ_i β_ai q_ai B_a⁻¹(ν_i∘c_a)
 *   s_p = √(c_a² + c_b²),  R_p = (s_p s_pᵀ) ∘ Σ + I,  h_p = ½ log|R_p|,  X_p = I − R_p⁻¹
 *   l_i = ν_i ∘ c_a²/s_p,  r_j = ν_j ∘ c_b²/s_p
 *   A_i = [X_p l_i, u_i, 1],  u_i = log α_a² + ½ (l_iᵀX_p l_i − ν_iᵀ diag(c_a²) ν_i)
 *   B_j = [r_j, 1, v_j],      v_j = log α_b² + ½ (r_jᵀX_p r_j − ν_jᵀ diag(c_b²) ν_j)
 *   S_p = Σ_ij W_p,ij exp(A_i·B_j)       (qtl_exp_sum_forward_lower of exp_sum.c, same library: for
 *                                         a = b, A_i·B_j = (X_p l_i)·l_j + u_i + u_j is symmetric in i, j
 *                                         for every operand, so the lower triangle gives S_p, and the
 *                                         lower form's G_A, G_B the same adjoint, from half the entries)
 *   cov_ab = exp(−h_p(a,b)) S_p(a,b) − mean_a mean_b      (the model variance diag(α²) is added by
 *                                                          the caller)
 * The backward pass is the hand-derived adjoint of all of the above: d(M⁻¹) = −M⁻¹ dM M⁻¹ and
 * d(½ log|M|) = ½ tr(M⁻¹ dM), symmetrized as `_InverseHalfLogdet` does, and the exp sums' adjoints
 * (Ā = S̄ G_A, B̄ = S̄ G_B, W̄ = S̄ exp(A Bᵀ)) from exp_sum.c: G_A and G_B saved by the forward pass
 * when W needs no gradient (the GP dynamics), recomputed by qtl_exp_sum_backward when it does
 * (the RBF policy, whose weights β_a β_bᵀ depend on ψ).
 *
 * Layout: the operands mean `... x D`, cov `... x D x D`, inputs `... x n x D`, beta `... x E x n`,
 * inv_ls `... x E x D`, log_sf2 `... x E`, weights `... x P x n x n` are each contiguous in their
 * trailing dimensions; their leading dimensions broadcast to the batch `batch[0..ndim)`, given by
 * one stride per batch dimension and operand (0 where the operand is broadcast), so broadcast
 * constants are never copied per item. Outputs are dense over the batch. Gradients are added into
 * buffers (zeroed by the caller) by the same per-operand strides, one item after the other, so
 * broadcast operands get their sums without races. The small per-item work (factorisations, mean,
 * gain, operands, adjoint: O((E + P) n D²)) runs in parallel over the items (each on its own
 * thread's scratch) wherever no two items write the same memory (the forward pass always; the
 * adjoint when no wanted gradient is broadcast, e.g. the GP dynamics' mean and cov only), else item
 * by item; each item's arithmetic is the same either way, so results do not depend on the thread
 * count. The n x n sums, the bulk, run in parallel in exp_sum.c with the thread count passed per call.
 *
 * Failure per item: where a B_a or R_p of an item is not positive definite, the forward pass with a
 * `failed` buffer (`items` flags) flags that item, makes its mean, covariance and gain NaN (its exp-sum
 * operands zero) and goes on with the others; the backward pass, given the same flags, adds NaN to every
 * gradient the item reaches, as the torch twin's NaN does. Without the buffer (NULL) such an item
 * ends the call with STATUS_NOT_PD, as before.
 *
 * Build: with exp_sum.c into one library (qtl/kernels/native/build.py):
 *   gcc -O3 -march=native -fno-math-errno -fopenmp -fPIC -shared -Wall -Wextra *.c -lm
 */
#include <math.h>
#include <omp.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* exp_sum.c (the same library): the fused weighted exponential sums and their gradients. */
int qtl_exp_sum_forward_lower(const double *a, const double *b, const double *w, const int64_t *off_a,
                              const int64_t *off_b, const int64_t *off_w, const int64_t *order, int64_t items,
                              int64_t n, int64_t m, int64_t k, const unsigned char *lower, double *out,
                              double *g_a, double *g_b, int threads);
int qtl_exp_sum_backward(const double *a, const double *b, const double *w, const int64_t *off_a,
                         const int64_t *off_b, const int64_t *off_w, const int64_t *order, int64_t items,
                         int64_t n, int64_t m, int64_t k, const double *grad_out, double *grad_a,
                         double *grad_b, double *grad_w, int threads);

enum { MEAN, COV, INPUTS, BETA, INV_LS, LOG_SF2, WEIGHTS, OPERANDS };
enum { GRAD_MEAN, GRAD_COV, GRAD_GAIN, GRAD_OUTS };
enum { STATUS_OK = 0, STATUS_NO_MEMORY = 1, STATUS_NOT_PD = 2, STATUS_ITEMS_FAILED = 3 };

/* The problem's sizes: items in the batch, n inputs, D input dims, E outputs, P pairs, K = D + 2. */
struct sizes {
    int64_t items, n, d, e, p, k;
};

/* One batch item's operands. */
struct item {
    const double *mean, *cov, *inputs, *beta, *inv_ls, *log_sf2, *weights;
};

/* Per-item quantities shared by forward and backward, and the pair indices (a, b) of each p. */
struct geometry {
    int64_t *pair_a, *pair_b;
    double *nu;    /* n x d: ν_i = x_i − μ */
    double *binv;  /* e x d x d: B_a⁻¹ */
    double *hb;    /* e: ½ log|B_a| */
    double *rinv;  /* p x d x d: R_p⁻¹ */
    double *hr;    /* p: ½ log|R_p| */
    double *scale; /* p x d: s_p */
    double *fac;   /* d x d: the factorisation's scratch */
    double *low;   /* d x d: the Cholesky factor */
};

/* Element offset of batch item `item` in an operand with batch strides `strides`. */
static int64_t item_offset(int64_t item, int64_t ndim, const int64_t *batch, const int64_t *strides)
{
    int64_t offset = 0;
    for (int64_t dim = ndim - 1; dim >= 0; --dim) {
        offset += (item % batch[dim]) * strides[dim];
        item /= batch[dim];
    }
    return offset;
}

static void *alloc_doubles(int64_t count) { return malloc((size_t)(count > 0 ? count : 1) * sizeof(double)); }

static void free_geometry(struct geometry *g)
{
    free(g->pair_a);
    free(g->pair_b);
    free(g->nu);
    free(g->binv);
    free(g->hb);
    free(g->rinv);
    free(g->hr);
    free(g->scale);
    free(g->fac);
    free(g->low);
}

/* Allocates a geometry and fills its pair indices (triu order); returns STATUS_OK or STATUS_NO_MEMORY. */
static int alloc_geometry(struct geometry *g, const struct sizes *sz)
{
    const int64_t d = sz->d;
    g->pair_a = malloc((size_t)sz->p * sizeof(int64_t));
    g->pair_b = malloc((size_t)sz->p * sizeof(int64_t));
    g->nu = alloc_doubles(sz->n * d);
    g->binv = alloc_doubles(sz->e * d * d);
    g->hb = alloc_doubles(sz->e);
    g->rinv = alloc_doubles(sz->p * d * d);
    g->hr = alloc_doubles(sz->p);
    g->scale = alloc_doubles(sz->p * d);
    g->fac = alloc_doubles(d * d);
    g->low = alloc_doubles(d * d);
    if (!g->pair_a || !g->pair_b || !g->nu || !g->binv || !g->hb || !g->rinv || !g->hr || !g->scale || !g->fac ||
        !g->low) {
        free_geometry(g);
        return STATUS_NO_MEMORY;
    }
    int64_t p = 0;
    for (int64_t a = 0; a < sz->e; ++a)
        for (int64_t b = a; b < sz->e; ++b) {
            g->pair_a[p] = a;
            g->pair_b[p] = b;
            ++p;
        }
    return STATUS_OK;
}

/* inv = M⁻¹ (exactly symmetric) and *half_logdet = ½ log|M| of the symmetric positive-definite M
 * (its lower triangle read from fac, which is overwritten); low: scratch for the Cholesky factor. */
static int spd_inverse(double *fac, double *low, int64_t d, double *inv, double *half_logdet)
{
    double total = 0.0;
    for (int64_t j = 0; j < d; ++j) {
        double diag = fac[j * d + j];
        for (int64_t k = 0; k < j; ++k)
            diag -= low[j * d + k] * low[j * d + k];
        if (!(diag > 0.0))
            return STATUS_NOT_PD;
        const double root = sqrt(diag);
        low[j * d + j] = root;
        total += log(root);
        for (int64_t i = j + 1; i < d; ++i) {
            double entry = fac[i * d + j];
            for (int64_t k = 0; k < j; ++k)
                entry -= low[i * d + k] * low[j * d + k];
            low[i * d + j] = entry / root;
        }
    }
    /* fac's lower triangle := L⁻¹, column by column */
    for (int64_t j = 0; j < d; ++j) {
        fac[j * d + j] = 1.0 / low[j * d + j];
        for (int64_t i = j + 1; i < d; ++i) {
            double entry = 0.0;
            for (int64_t k = j; k < i; ++k)
                entry += low[i * d + k] * fac[k * d + j];
            fac[i * d + j] = -entry / low[i * d + i];
        }
    }
    /* M⁻¹ = L⁻ᵀ L⁻¹, one triangle computed, mirrored */
    for (int64_t i = 0; i < d; ++i)
        for (int64_t j = 0; j <= i; ++j) {
            double entry = 0.0;
            for (int64_t k = i; k < d; ++k)
                entry += fac[k * d + i] * fac[k * d + j];
            inv[i * d + j] = entry;
            inv[j * d + i] = entry;
        }
    *half_logdet = total;
    return STATUS_OK;
}

/* (scale scaleᵀ) ∘ Σ + I into fac, then its inverse and half log-determinant. */
static int scaled_inverse(const double *cov, const double *scale, struct geometry *g, int64_t d, double *inv,
                          double *half_logdet)
{
    for (int64_t i = 0; i < d; ++i)
        for (int64_t j = 0; j < d; ++j)
            g->fac[i * d + j] = scale[i] * scale[j] * cov[i * d + j] + (i == j ? 1.0 : 0.0);
    return spd_inverse(g->fac, g->low, d, inv, half_logdet);
}

/* ν, B_a⁻¹, h_a, s_p, R_p⁻¹ and h_p of one item. */
static int item_geometry(const struct sizes *sz, const struct item *it, struct geometry *g)
{
    const int64_t n = sz->n, d = sz->d;
    for (int64_t i = 0; i < n; ++i)
        for (int64_t k = 0; k < d; ++k)
            g->nu[i * d + k] = it->inputs[i * d + k] - it->mean[k];
    for (int64_t a = 0; a < sz->e; ++a)
        if (scaled_inverse(it->cov, it->inv_ls + a * d, g, d, g->binv + a * d * d, g->hb + a))
            return STATUS_NOT_PD;
    for (int64_t p = 0; p < sz->p; ++p) {
        const double *ca = it->inv_ls + g->pair_a[p] * d, *cb = it->inv_ls + g->pair_b[p] * d;
        double *s = g->scale + p * d;
        for (int64_t k = 0; k < d; ++k)
            s[k] = sqrt(ca[k] * ca[k] + cb[k] * cb[k]);
        if (scaled_inverse(it->cov, s, g, d, g->rinv + p * d * d, g->hr + p))
            return STATUS_NOT_PD;
    }
    return STATUS_OK;
}

/* mean `e` and gain `d x e` of one item; vec: scratch of 3 d. */
static void item_mean_gain(const struct sizes *sz, const struct item *it, const struct geometry *g, double *mean,
                           double *gain, double *vec)
{
    const int64_t n = sz->n, d = sz->d, e = sz->e;
    double *scaled = vec, *solved = vec + d, *total = vec + 2 * d;
    for (int64_t a = 0; a < e; ++a) {
        const double *c = it->inv_ls + a * d, *binv = g->binv + a * d * d;
        const double log_norm = it->log_sf2[a] - g->hb[a];
        double sum = 0.0;
        memset(total, 0, (size_t)d * sizeof(double));
        for (int64_t i = 0; i < n; ++i) {
            const double *nu = g->nu + i * d;
            for (int64_t k = 0; k < d; ++k)
                scaled[k] = nu[k] * c[k];
            double quad = 0.0;
            for (int64_t l = 0; l < d; ++l) {
                double entry = 0.0;
                for (int64_t k = 0; k < d; ++k)
                    entry += scaled[k] * binv[k * d + l];
                solved[l] = entry;
                quad += scaled[l] * entry;
            }
            const double bq = it->beta[a * n + i] * exp(log_norm - 0.5 * quad);
            sum += bq;
            for (int64_t l = 0; l < d; ++l)
                total[l] += bq * solved[l];
        }
        mean[a] = sum;
        for (int64_t k = 0; k < d; ++k)
            gain[k * e + a] = total[k] * c[k];
    }
}

/* `count` NaNs from dst on. */
static void fill_nan(double *dst, int64_t count)
{
    for (int64_t i = 0; i < count; ++i)
        dst[i] = NAN;
}

/* X_p = I − R_p⁻¹ into x; c_a²/s_p, c_b²/s_p into left, right; c_a², c_b² into sq_a, sq_b. */
static void pair_maps(const struct sizes *sz, const struct item *it, const struct geometry *g, int64_t p, double *x,
                      double *left, double *right, double *sq_a, double *sq_b)
{
    const int64_t d = sz->d;
    const double *rinv = g->rinv + p * d * d, *s = g->scale + p * d;
    const double *ca = it->inv_ls + g->pair_a[p] * d, *cb = it->inv_ls + g->pair_b[p] * d;
    for (int64_t i = 0; i < d * d; ++i)
        x[i] = ((i % (d + 1)) == 0 ? 1.0 : 0.0) - rinv[i];
    for (int64_t k = 0; k < d; ++k) {
        sq_a[k] = ca[k] * ca[k];
        sq_b[k] = cb[k] * cb[k];
        left[k] = sq_a[k] / s[k];
        right[k] = sq_b[k] / s[k];
    }
}

/* out = v X (row vector times X), d entries. */
static void row_times(const double *v, const double *x, int64_t d, double *out)
{
    for (int64_t l = 0; l < d; ++l) {
        double entry = 0.0;
        for (int64_t k = 0; k < d; ++k)
            entry += v[k] * x[k * d + l];
        out[l] = entry;
    }
}

/* The exp-sum operands A, B `p x n x k` of one item; vec: scratch of 8 d + d². */
static void item_operands(const struct sizes *sz, const struct item *it, const struct geometry *g, double *lhs,
                          double *rhs, double *vec)
{
    const int64_t n = sz->n, d = sz->d, k = sz->k;
    double *left = vec, *right = vec + d, *sq_a = vec + 2 * d, *sq_b = vec + 3 * d, *side = vec + 4 * d;
    double *side_x = vec + 5 * d, *x = vec + 8 * d;
    for (int64_t p = 0; p < sz->p; ++p) {
        pair_maps(sz, it, g, p, x, left, right, sq_a, sq_b);
        const double log_a = it->log_sf2[g->pair_a[p]], log_b = it->log_sf2[g->pair_b[p]];
        for (int64_t i = 0; i < n; ++i) {
            const double *nu = g->nu + i * d;
            double *row_a = lhs + (p * n + i) * k, *row_b = rhs + (p * n + i) * k;
            for (int64_t l = 0; l < d; ++l)
                side[l] = nu[l] * left[l];
            row_times(side, x, d, side_x);
            double quad = 0.0;
            for (int64_t l = 0; l < d; ++l) {
                row_a[l] = side_x[l];
                quad += side_x[l] * side[l] - nu[l] * nu[l] * sq_a[l];
            }
            row_a[d] = log_a + 0.5 * quad;
            row_a[d + 1] = 1.0;
            for (int64_t l = 0; l < d; ++l)
                side[l] = nu[l] * right[l];
            row_times(side, x, d, side_x);
            quad = 0.0;
            for (int64_t l = 0; l < d; ++l) {
                row_b[l] = side[l];
                quad += side_x[l] * side[l] - nu[l] * nu[l] * sq_b[l];
            }
            row_b[d] = 1.0;
            row_b[d + 1] = log_b + 0.5 * quad;
        }
    }
}

/* Scratch vector length of item_operands and the adjoint. */
static int64_t vec_len(int64_t d) { return 12 * d + 4 * d * d; }

/* offsets[op * items + item] for `count` operands with batch strides strides[op * ndim + dim]. */
static int64_t *all_offsets(int64_t count, int64_t items, int64_t ndim, const int64_t *batch, const int64_t *strides)
{
    int64_t *offsets = malloc((size_t)(count * items > 0 ? count * items : 1) * sizeof(int64_t));
    if (offsets)
        for (int64_t op = 0; op < count; ++op)
            for (int64_t item = 0; item < items; ++item)
                offsets[op * items + item] = item_offset(item, ndim, batch, strides + op * ndim);
    return offsets;
}

static struct item item_at(const double *const *operand, const int64_t *offsets, int64_t items, int64_t b)
{
    const struct item it = {
        .mean = operand[MEAN] + offsets[MEAN * items + b],
        .cov = operand[COV] + offsets[COV * items + b],
        .inputs = operand[INPUTS] + offsets[INPUTS * items + b],
        .beta = operand[BETA] + offsets[BETA * items + b],
        .inv_ls = operand[INV_LS] + offsets[INV_LS * items + b],
        .log_sf2 = operand[LOG_SF2] + offsets[LOG_SF2 * items + b],
        .weights = operand[WEIGHTS] + offsets[WEIGHTS * items + b],
    };
    return it;
}

/* The exp sums' per-(item, pair) offsets: A and B dense, W by the items' W offsets; `order` groups
 * the (item, pair)s that share a W (stably by W offset). Returns NULL when memory is short. */
static int64_t *sum_offsets(const struct sizes *sz, const int64_t *w_offsets)
{
    const int64_t count = sz->items * sz->p, nn = sz->n * sz->n, nk = sz->n * sz->k;
    int64_t *out = malloc((size_t)(4 * count > 0 ? 4 * count : 1) * sizeof(int64_t));
    if (!out)
        return NULL;
    int64_t *off_ab = out, *off_w = out + count, *order = out + 2 * count, *keys = out + 3 * count;
    for (int64_t b = 0; b < sz->items; ++b)
        for (int64_t p = 0; p < sz->p; ++p) {
            const int64_t ip = b * sz->p + p;
            off_ab[ip] = ip * nk;
            off_w[ip] = w_offsets[b] + p * nn;
        }
    /* insertion sort of the indices by W offset (stable; count is small) */
    for (int64_t ip = 0; ip < count; ++ip) {
        int64_t pos = ip;
        while (pos > 0 && keys[pos - 1] > off_w[ip]) {
            keys[pos] = keys[pos - 1];
            order[pos] = order[pos - 1];
            --pos;
        }
        keys[pos] = off_w[ip];
        order[pos] = ip;
    }
    return out;
}

/* What the per-item forward work reads, and the per-item memory it writes. */
struct forward_ctx {
    const struct sizes *sz;
    const double *const *operand;
    const int64_t *offsets;
    unsigned char *failed;
    double *out_mean, *gain, *lhs, *rhs, *hr;
};

/* Item b's geometry, mean, gain and exp-sum operands (NaN outputs and zero operands where it is flagged failed);
 * g and vec (vec_len(d)): scratch. Returns a status (STATUS_OK for a flagged item). */
static int item_forward(const struct forward_ctx *c, int64_t b, struct geometry *g, double *vec)
{
    const struct sizes *sz = c->sz;
    const int64_t d = sz->d, e = sz->e, block = sz->n * sz->k;
    const struct item it = item_at(c->operand, c->offsets, sz->items, b);
    const int status = item_geometry(sz, &it, g);
    if (c->failed)
        c->failed[b] = status == STATUS_NOT_PD;
    if (status == STATUS_NOT_PD && c->failed) { /* NaN outputs; zero operands keep its exp sums finite */
        fill_nan(c->out_mean + b * e, e);
        fill_nan(c->gain + b * d * e, d * e);
        memset(c->lhs + b * sz->p * block, 0, (size_t)(sz->p * block) * sizeof(double));
        memset(c->rhs + b * sz->p * block, 0, (size_t)(sz->p * block) * sizeof(double));
        memset(c->hr + b * sz->p, 0, (size_t)sz->p * sizeof(double));
        return STATUS_OK;
    }
    if (status)
        return status;
    item_mean_gain(sz, &it, g, c->out_mean + b * e, c->gain + b * d * e, vec);
    item_operands(sz, &it, g, c->lhs + b * sz->p * block, c->rhs + b * sz->p * block, vec);
    memcpy(c->hr + b * sz->p, g->hr, (size_t)sz->p * sizeof(double));
    return STATUS_OK;
}

/* item_forward of every item on `workers` threads, each with its own scratch; returns the first failing
 * item's status, or STATUS_OK. */
static int parallel_items(const struct forward_ctx *c, int workers)
{
    const int64_t items = c->sz->items;
    struct geometry *geo = calloc((size_t)workers, sizeof(*geo));
    double **vecs = calloc((size_t)workers, sizeof(*vecs));
    int *statuses = calloc((size_t)(items > 0 ? items : 1), sizeof(int));
    int status = geo && vecs && statuses ? STATUS_OK : STATUS_NO_MEMORY;
    int made = 0;
    for (; made < workers && status == STATUS_OK; ++made) {
        status = alloc_geometry(geo + made, c->sz);
        vecs[made] = status == STATUS_OK ? alloc_doubles(vec_len(c->sz->d)) : NULL;
        if (status == STATUS_OK && !vecs[made]) {
            free_geometry(geo + made);
            status = STATUS_NO_MEMORY;
        }
    }
    if (status == STATUS_OK) {
#pragma omp parallel for num_threads(workers) schedule(static)
        for (int64_t b = 0; b < items; ++b) {
            const int w = omp_get_thread_num();
            statuses[b] = item_forward(c, b, geo + w, vecs[w]);
        }
        for (int64_t b = 0; b < items && status == STATUS_OK; ++b)
            status = statuses[b];
    } else if (made > 0)
        --made; /* the failed one freed itself */
    for (int w = 0; w < made; ++w) {
        free_geometry(geo + w);
        free(vecs[w]);
    }
    free(statuses);
    free(vecs);
    free(geo);
    return status;
}

/* work: the sums `items x p`, the means `items x e` (for the backward pass), then (with_grads) G_A
 * and G_B `items x p x n x k` each; failed `items` (or NULL): 1 for an item whose B_a or R_p is not
 * positive definite (its outputs NaN), else 0; lower_pairs: the a = b pairs' sums from their lower
 * triangles (0: every pair's full n x n sum, as before). Returns 0, 1 when memory is short, 2 when a
 * B_a or R_p is not positive definite and failed is NULL, 3 when it is and failed flags the item(s). */
int qtl_se_moments_forward(const double *const *operand, int64_t ndim, const int64_t *batch, const int64_t *strides,
                           int64_t n, int64_t d, int64_t e, double *out_mean, double *out_cov, double *gain,
                           double *work, unsigned char *failed, int with_grads, int lower_pairs, int threads)
{
    int64_t items = 1;
    for (int64_t dim = 0; dim < ndim; ++dim)
        items *= batch[dim];
    const struct sizes sz = {.items = items, .n = n, .d = d, .e = e, .p = e * (e + 1) / 2, .k = d + 2};
    const int64_t count = items * sz.p, block = n * sz.k;
    struct geometry g;
    if (alloc_geometry(&g, &sz))
        return STATUS_NO_MEMORY;
    int64_t *offsets = all_offsets(OPERANDS, items, ndim, batch, strides);
    int64_t *sum_off = offsets ? sum_offsets(&sz, offsets + WEIGHTS * items) : NULL;
    double *lhs = alloc_doubles(count * block), *rhs = alloc_doubles(count * block);
    double *hr = alloc_doubles(count), *vec = alloc_doubles(vec_len(d));
    unsigned char *lower = malloc((size_t)(count > 0 ? count : 1)); /* the a = b pairs: symmetric sums */
    int status = (!offsets || !sum_off || !lhs || !rhs || !hr || !vec || !lower) ? STATUS_NO_MEMORY : STATUS_OK;
    const struct forward_ctx ctx = {
        .sz = &sz, .operand = operand, .offsets = offsets, .failed = failed, .out_mean = out_mean, .gain = gain,
        .lhs = lhs, .rhs = rhs, .hr = hr,
    };
    const int workers = threads < items ? threads : (int)items;
    if (status == STATUS_OK && workers > 1) /* the items' own memory only: in parallel, the same arithmetic */
        status = parallel_items(&ctx, workers);
    for (int64_t b = 0; workers <= 1 && b < items && status == STATUS_OK; ++b)
        status = item_forward(&ctx, b, &g, vec);
    if (status == STATUS_OK) {
        double *sums = work, *ops = work + count + items * e;
        double *g_a = with_grads ? ops : NULL, *g_b = with_grads ? ops + count * block : NULL;
        for (int64_t b = 0; b < items; ++b)
            for (int64_t p = 0; p < sz.p; ++p)
                lower[b * sz.p + p] = lower_pairs && g.pair_a[p] == g.pair_b[p];
        if (qtl_exp_sum_forward_lower(lhs, rhs, operand[WEIGHTS], sum_off, sum_off, sum_off + count,
                                      sum_off + 2 * count, count, n, n, sz.k, lower, sums, g_a, g_b, threads))
            status = STATUS_NO_MEMORY;
        else
            for (int64_t b = 0; b < items; ++b) {
                const double *m = out_mean + b * e;
                double *cov = out_cov + b * e * e;
                memcpy(work + count + b * e, m, (size_t)e * sizeof(double));
                if (failed && failed[b]) {
                    fill_nan(cov, e * e);
                    continue;
                }
                for (int64_t p = 0; p < sz.p; ++p) {
                    const int64_t a = g.pair_a[p], c = g.pair_b[p];
                    const double second = exp(-hr[b * sz.p + p]) * sums[b * sz.p + p];
                    cov[a * e + c] = second - m[a] * m[c];
                    cov[c * e + a] = second - m[c] * m[a];
                }
            }
    }
    for (int64_t b = 0; failed && b < items && status == STATUS_OK; ++b)
        if (failed[b])
            status = STATUS_ITEMS_FAILED;
    free(lower);
    free(vec);
    free(hr);
    free(rhs);
    free(lhs);
    free(sum_off);
    free(offsets);
    free_geometry(&g);
    return status;
}

/* Scratch of the adjoint of one item. */
struct adjoint {
    double *nu_bar;  /* n x d */
    double *c_bar;   /* e x d: ∂/∂c_a, direct */
    double *sq_bar;  /* e x d: ∂/∂(c_a²) */
    double *mat_bar; /* d x d: ∂/∂(B_a⁻¹) or ∂/∂X_p */
    double *tmp;     /* d x d */
    double *cov_bar; /* d x d */
    double *vec;     /* vec_len(d) */
};

/* ∂/∂M of (M⁻¹, ½ log|M|) given inv = M⁻¹, inv_bar = ∂/∂M⁻¹ (overwritten with ∂/∂M) and h_bar:
 * sym(−M⁻¹ inv_bar M⁻¹ + ½ h_bar M⁻¹); then the scale's and Σ's shares for M = (s sᵀ) ∘ Σ + I. */
static void scaled_inverse_adjoint(const double *inv, double *inv_bar, double h_bar, const double *cov,
                                   const double *scale, int64_t d, double *tmp, double *cov_bar, double *scale_bar)
{
    for (int64_t i = 0; i < d; ++i) /* tmp = M⁻¹ inv_bar */
        for (int64_t j = 0; j < d; ++j) {
            double entry = 0.0;
            for (int64_t k = 0; k < d; ++k)
                entry += inv[i * d + k] * inv_bar[k * d + j];
            tmp[i * d + j] = entry;
        }
    for (int64_t i = 0; i < d; ++i) /* inv_bar = −tmp M⁻¹ + ½ h_bar M⁻¹ */
        for (int64_t j = 0; j < d; ++j) {
            double entry = 0.0;
            for (int64_t k = 0; k < d; ++k)
                entry += tmp[i * d + k] * inv[k * d + j];
            inv_bar[i * d + j] = -entry + inv[i * d + j] * (0.5 * h_bar);
        }
    for (int64_t i = 0; i < d; ++i)
        for (int64_t j = 0; j <= i; ++j) {
            const double sym = 0.5 * (inv_bar[i * d + j] + inv_bar[j * d + i]);
            inv_bar[i * d + j] = sym;
            inv_bar[j * d + i] = sym;
        }
    for (int64_t k = 0; k < d; ++k) {
        double entry = 0.0;
        for (int64_t l = 0; l < d; ++l) {
            const double m_bar = inv_bar[k * d + l];
            cov_bar[k * d + l] += scale[k] * scale[l] * m_bar;
            entry += (m_bar * cov[k * d + l] + inv_bar[l * d + k] * cov[l * d + k]) * scale[l];
        }
        scale_bar[k] += entry;
    }
}

/* Gradient buffers of one item (NULL where not wanted); dense views of its output gradients. */
struct item_grads {
    double *mean, *cov, *inputs, *beta, *inv_ls, *log_sf2;
    const double *g_mean, *g_cov, *g_gain; /* e, e x e, d x e (zeros where the output had none) */
};

/* The gradient outputs of item b (NULL where that operand's gradient is not asked for); no output gradients yet. */
static struct item_grads item_grads_at(double *const *grad, const int64_t *grad_off, int64_t items, int64_t b)
{
    const struct item_grads gr = {
        .mean = grad[MEAN] ? grad[MEAN] + grad_off[MEAN * items + b] : NULL,
        .cov = grad[COV] ? grad[COV] + grad_off[COV * items + b] : NULL,
        .inputs = grad[INPUTS] ? grad[INPUTS] + grad_off[INPUTS * items + b] : NULL,
        .beta = grad[BETA] ? grad[BETA] + grad_off[BETA * items + b] : NULL,
        .inv_ls = grad[INV_LS] ? grad[INV_LS] + grad_off[INV_LS * items + b] : NULL,
        .log_sf2 = grad[LOG_SF2] ? grad[LOG_SF2] + grad_off[LOG_SF2 * items + b] : NULL,
    };
    return gr;
}

/* The mean and gain's share of the adjoint of one item, given m̄ (`e`, cov's share included). */
static void mean_gain_adjoint(const struct sizes *sz, const struct item *it, const struct geometry *g,
                              const double *mean_bar, const struct item_grads *gr, struct adjoint *adj)
{
    const int64_t n = sz->n, d = sz->d, e = sz->e;
    double *scaled = adj->vec, *solved = scaled + d, *total = solved + d, *t_bar = total + d;
    double *solved_bar = t_bar + d, *scaled_bar = solved_bar + d, *scale_bar = scaled_bar + d;
    for (int64_t a = 0; a < e; ++a) {
        const double *c = it->inv_ls + a * d, *binv = g->binv + a * d * d;
        const double log_norm = it->log_sf2[a] - g->hb[a];
        double *c_bar = adj->c_bar + a * d;
        double log_q_sum = 0.0;
        memset(total, 0, (size_t)d * sizeof(double));
        memset(adj->mat_bar, 0, (size_t)(d * d) * sizeof(double));
        for (int64_t k = 0; k < d; ++k)
            t_bar[k] = gr->g_gain[k * e + a] * c[k];
        for (int64_t i = 0; i < n; ++i) {
            const double *nu = g->nu + i * d;
            for (int64_t k = 0; k < d; ++k)
                scaled[k] = nu[k] * c[k];
            double quad = 0.0;
            row_times(scaled, binv, d, solved);
            for (int64_t l = 0; l < d; ++l)
                quad += scaled[l] * solved[l];
            const double q = exp(log_norm - 0.5 * quad), bq = it->beta[a * n + i] * q;
            double bq_bar = mean_bar[a];
            for (int64_t l = 0; l < d; ++l) {
                total[l] += bq * solved[l];
                bq_bar += t_bar[l] * solved[l];
            }
            if (gr->beta)
                gr->beta[a * n + i] += bq_bar * q;
            const double log_q_bar = bq_bar * bq;
            log_q_sum += log_q_bar;
            for (int64_t l = 0; l < d; ++l)
                solved_bar[l] = bq * t_bar[l] - 0.5 * log_q_bar * scaled[l];
            row_times(solved_bar, binv, d, scaled_bar); /* B⁻¹ symmetric */
            double *nu_bar = adj->nu_bar + i * d;
            for (int64_t k = 0; k < d; ++k) {
                scaled_bar[k] -= 0.5 * log_q_bar * solved[k];
                for (int64_t l = 0; l < d; ++l)
                    adj->mat_bar[k * d + l] += scaled[k] * solved_bar[l];
                nu_bar[k] += scaled_bar[k] * c[k];
                c_bar[k] += scaled_bar[k] * nu[k];
            }
        }
        if (gr->log_sf2)
            gr->log_sf2[a] += log_q_sum;
        memset(scale_bar, 0, (size_t)d * sizeof(double));
        scaled_inverse_adjoint(binv, adj->mat_bar, -log_q_sum, it->cov, c, d, adj->tmp, adj->cov_bar, scale_bar);
        for (int64_t k = 0; k < d; ++k)
            c_bar[k] += gr->g_gain[k * e + a] * total[k] + scale_bar[k];
    }
}

/* One side of a pair's operand adjoint: for rows side_i = ν_i ∘ map, given their operand gradients
 * (`n x k`, times `weight`; col: the column of u or v), adds into ν̄, X̄, map̄, (c²)̄ and returns Σ ū.
 * With_x: the operand holds X side_i (the a-side) rather than side_i (the b-side). */
static double side_adjoint(const struct sizes *sz, const struct geometry *g, const double *x, const double *map,
                           const double *sq, const double *ops_bar, double weight, int64_t col, int with_x,
                           struct adjoint *adj, double *map_bar, double *sq_bar)
{
    const int64_t n = sz->n, d = sz->d, k = sz->k;
    double *side = adj->vec, *side_x = side + d, *direct = side_x + d, *side_bar = direct + d, *pre = side_bar + d;
    double u_sum = 0.0;
    for (int64_t i = 0; i < n; ++i) {
        const double *nu = g->nu + i * d, *row = ops_bar + i * k;
        const double u_bar = weight * row[col];
        u_sum += u_bar;
        for (int64_t l = 0; l < d; ++l)
            side[l] = nu[l] * map[l];
        row_times(side, x, d, side_x);
        /* quad = (X side)·side: ∂/∂(X side) = ½ ū side, ∂/∂side = ½ ū X side; plus the operand's own */
        for (int64_t l = 0; l < d; ++l) {
            direct[l] = weight * row[l];
            pre[l] = 0.5 * u_bar * side[l] + (with_x ? direct[l] : 0.0); /* ∂/∂(X side) */
        }
        row_times(pre, x, d, side_bar); /* X symmetric */
        double *nu_bar = adj->nu_bar + i * d;
        for (int64_t l = 0; l < d; ++l) {
            side_bar[l] += 0.5 * u_bar * side_x[l] + (with_x ? 0.0 : direct[l]);
            for (int64_t m = 0; m < d; ++m)
                adj->mat_bar[l * d + m] += side[l] * pre[m];
            nu_bar[l] += side_bar[l] * map[l] - u_bar * nu[l] * sq[l];
            map_bar[l] += side_bar[l] * nu[l];
            sq_bar[l] -= 0.5 * u_bar * nu[l] * nu[l];
        }
    }
    return u_sum;
}

/* The pairs' share of the adjoint of one item: sums S_p, S̄_p (already exp(−h_p)-scaled), operand
 * gradients G_A, G_B (`p x n x k`, times op_scale[p]). */
static void pairs_adjoint(const struct sizes *sz, const struct item *it, const struct geometry *g, const double *sums,
                          const double *sum_bar, const double *ga, const double *gb, const double *op_scale,
                          const struct item_grads *gr, struct adjoint *adj)
{
    const int64_t n = sz->n, d = sz->d, k = sz->k;
    double *maps = adj->vec + 6 * d; /* left, right, sq_a, sq_b, left_bar, right_bar, scale_bar */
    double *left = maps, *right = maps + d, *sq_a = right + d, *sq_b = sq_a + d;
    double *left_bar = sq_b + d, *right_bar = left_bar + d;
    double *x = adj->vec + 12 * d, *scale_bar = adj->tmp + d * d; /* tmp holds 2 d² */
    for (int64_t p = 0; p < sz->p; ++p) {
        if (sum_bar[p] == 0.0)
            continue;
        const int64_t a = g->pair_a[p], b = g->pair_b[p];
        const double *s = g->scale + p * d;
        pair_maps(sz, it, g, p, x, left, right, sq_a, sq_b);
        memset(adj->mat_bar, 0, (size_t)(d * d) * sizeof(double));
        memset(left_bar, 0, (size_t)(2 * d) * sizeof(double));
        double *sq_bar_a = adj->sq_bar + a * d, *sq_bar_b = adj->sq_bar + b * d;
        const double w = op_scale[p];
        const double u_sum = side_adjoint(sz, g, x, left, sq_a, ga + p * n * k, w, d, 1, adj, left_bar, sq_bar_a);
        const double v_sum = side_adjoint(sz, g, x, right, sq_b, gb + p * n * k, w, d + 1, 0, adj, right_bar, sq_bar_b);
        if (gr->log_sf2) {
            gr->log_sf2[a] += u_sum;
            gr->log_sf2[b] += v_sum;
        }
        /* second_p = exp(−h_p) S_p: h̄_p = −second_p second̄_p = −S_p S̄_p (S̄_p = exp(−h_p) second̄_p) */
        const double h_bar = -sums[p] * sum_bar[p];
        for (int64_t i = 0; i < d * d; ++i) /* X = I − R⁻¹ */
            adj->mat_bar[i] = -adj->mat_bar[i];
        memset(scale_bar, 0, (size_t)d * sizeof(double));
        scaled_inverse_adjoint(g->rinv + p * d * d, adj->mat_bar, h_bar, it->cov, s, d, adj->tmp, adj->cov_bar,
                               scale_bar);
        for (int64_t l = 0; l < d; ++l) {
            /* left = c_a²/s, right = c_b²/s, s = √(c_a² + c_b²) */
            scale_bar[l] -= (left_bar[l] * sq_a[l] + right_bar[l] * sq_b[l]) / (s[l] * s[l]);
            const double via_s = scale_bar[l] / (2.0 * s[l]);
            sq_bar_a[l] += left_bar[l] / s[l] + via_s;
            sq_bar_b[l] += right_bar[l] / s[l] + via_s;
        }
    }
}

/* The output gradients of item b, dense (zeros where an output has none): mean `e`, cov `e x e`,
 * gain `d x e`; grad_out_strides: per output, the batch strides then the inner ones (`ndim + 2`). */
static void read_output_grads(const double *const *grad_out, const int64_t *grad_out_strides, int64_t ndim,
                              const int64_t *batch, int64_t b, int64_t d, int64_t e, double *g_mean, double *g_cov,
                              double *g_gain)
{
    const int64_t width = ndim + 2;
    const int64_t rows[GRAD_OUTS] = {1, e, d}, cols[GRAD_OUTS] = {e, e, e};
    double *dense[GRAD_OUTS] = {g_mean, g_cov, g_gain};
    for (int out = 0; out < GRAD_OUTS; ++out) {
        const int64_t *st = grad_out_strides + out * width;
        const double *src = grad_out[out] ? grad_out[out] + item_offset(b, ndim, batch, st) : NULL;
        /* mean has one inner dimension: its stride is st[ndim] */
        const int64_t row_stride = out == GRAD_MEAN ? 0 : st[ndim], col_stride = out == GRAD_MEAN ? st[ndim] : st[ndim + 1];
        for (int64_t r = 0; r < rows[out]; ++r)
            for (int64_t c = 0; c < cols[out]; ++c)
                dense[out][r * cols[out] + c] = src ? src[r * row_stride + c * col_stride] : 0.0;
    }
}

/* S̄_p = exp(−h_p) second̄_p, second̄_p = Σ of cov's gradient over the (a, b) with pair p. */
static void sum_grads(const struct sizes *sz, const struct geometry *g, const double *g_cov, double *sum_bar)
{
    const int64_t e = sz->e;
    for (int64_t p = 0; p < sz->p; ++p) {
        const int64_t a = g->pair_a[p], c = g->pair_b[p];
        const double bar = a == c ? g_cov[a * e + a] : g_cov[a * e + c] + g_cov[c * e + a];
        sum_bar[p] = exp(-g->hr[p]) * bar;
    }
}

/* NaN added to the gradients `gr` of a failed item, W̄ (w_grad, `p x n x n`, or NULL) included. */
static void poison_item(const struct sizes *sz, const struct item_grads *gr, double *w_grad)
{
    const int64_t n = sz->n, d = sz->d, e = sz->e;
    double *const parts[] = {gr->mean, gr->cov, gr->inputs, gr->beta, gr->inv_ls, gr->log_sf2, w_grad};
    const int64_t sizes[] = {d, d * d, n * d, e * n, e * d, e, sz->p * n * n};
    for (int part = 0; part < 7; ++part)
        for (int64_t i = 0; parts[part] && i < sizes[part]; ++i)
            parts[part][i] += NAN;
}

/* What the adjoint of every item reads (and the per-item memory it writes), shared by the items. */
struct backward_ctx {
    const struct sizes *sz;
    const double *const *operand;
    const int64_t *offsets;
    double *const *grad;
    const int64_t *grad_off;
    const unsigned char *failed;
    int pairs, need_ops, fused;
    const double *const *grad_out;
    const int64_t *grad_out_strides;
    int64_t ndim;
    const int64_t *batch;
    double *sum_bar;
    const double *work, *out_mean, *ops, *ga, *gb, *ones;
};

/* One worker's scratch of the adjoint: the geometry, the adjoint's buffers and the dense output gradients. */
struct adjoint_scratch {
    struct geometry g;
    struct adjoint adj;
    double *dense; /* 2 e + e² + d e */
};

static void free_adjoint_scratch(struct adjoint_scratch *s)
{
    free(s->adj.nu_bar);
    free(s->adj.c_bar);
    free(s->adj.sq_bar);
    free(s->adj.mat_bar);
    free(s->adj.tmp);
    free(s->adj.cov_bar);
    free(s->adj.vec);
    free(s->dense);
    free_geometry(&s->g);
}

/* Allocates one worker's scratch; returns STATUS_OK or STATUS_NO_MEMORY (then nothing is left allocated). */
static int alloc_adjoint_scratch(struct adjoint_scratch *s, const struct sizes *sz)
{
    const int64_t n = sz->n, d = sz->d, e = sz->e;
    memset(s, 0, sizeof(*s));
    if (alloc_geometry(&s->g, sz))
        return STATUS_NO_MEMORY;
    s->adj.nu_bar = alloc_doubles(n * d);
    s->adj.c_bar = alloc_doubles(e * d);
    s->adj.sq_bar = alloc_doubles(e * d);
    s->adj.mat_bar = alloc_doubles(d * d);
    s->adj.tmp = alloc_doubles(2 * d * d);
    s->adj.cov_bar = alloc_doubles(d * d);
    s->adj.vec = alloc_doubles(vec_len(d));
    s->dense = alloc_doubles(2 * e + e * e + d * e);
    if (!s->adj.nu_bar || !s->adj.c_bar || !s->adj.sq_bar || !s->adj.mat_bar || !s->adj.tmp || !s->adj.cov_bar ||
        !s->adj.vec || !s->dense) {
        free_adjoint_scratch(s);
        return STATUS_NO_MEMORY;
    }
    return STATUS_OK;
}

/* Whether the items' gradient memory is disjoint: every wanted gradient's item offsets increase by at least
 * one item's size (none broadcast), so that items may add into their own in parallel. */
static int disjoint_items(const struct sizes *sz, double *const *grad, const int64_t *grad_off, int pairs)
{
    const int64_t n = sz->n, d = sz->d, e = sz->e;
    const int64_t sizes[OPERANDS] = {d, d * d, n * d, e * n, e * d, e, sz->p * n * n};
    for (int op = 0; op < OPERANDS; ++op) {
        if (!grad[op] || (op == WEIGHTS && !pairs))
            continue;
        for (int64_t b = 1; b < sz->items; ++b)
            if (grad_off[op * sz->items + b] - grad_off[op * sz->items + b - 1] < sizes[op])
                return 0;
    }
    return 1;
}

/* The adjoint of item b into its gradients (poisoned where the forward pass flagged it); returns a status. */
static int item_adjoint(const struct backward_ctx *c, int64_t b, struct adjoint_scratch *s)
{
    const struct sizes *sz = c->sz;
    const int64_t items = sz->items, n = sz->n, d = sz->d, e = sz->e, block = n * sz->k, count = items * sz->p;
    double *const *grad = c->grad;
    if (c->failed && c->failed[b]) {
        const struct item_grads bad = item_grads_at(grad, c->grad_off, items, b);
        poison_item(sz, &bad, c->pairs && grad[WEIGHTS] ? grad[WEIGHTS] + c->grad_off[WEIGHTS * items + b] : NULL);
        return STATUS_OK;
    }
    if (!(c->need_ops || grad[BETA]))
        return STATUS_OK;
    struct geometry *g = &s->g;
    struct adjoint *adj = &s->adj;
    double *const g_mean = s->dense, *const g_cov = g_mean + e, *const g_gain = g_cov + e * e;
    double *const m_bar = g_gain + d * e;
    const struct item it = item_at(c->operand, c->offsets, items, b);
    const int status = item_geometry(sz, &it, g);
    if (status)
        return status;
    read_output_grads(c->grad_out, c->grad_out_strides, c->ndim, c->batch, b, d, e, g_mean, g_cov, g_gain);
    sum_grads(sz, g, g_cov, c->sum_bar + b * sz->p);
    const double *m = c->out_mean + b * e;
    for (int64_t a = 0; a < e; ++a) { /* cov_ab = … − m_a m_b */
        double entry = g_mean[a];
        for (int64_t col = 0; col < e; ++col)
            entry -= (g_cov[a * e + col] + g_cov[col * e + a]) * m[col];
        m_bar[a] = entry;
    }
    struct item_grads gr = item_grads_at(grad, c->grad_off, items, b);
    gr.g_mean = g_mean;
    gr.g_cov = g_cov;
    gr.g_gain = g_gain;
    memset(adj->nu_bar, 0, (size_t)(n * d) * sizeof(double));
    memset(adj->c_bar, 0, (size_t)(e * d) * sizeof(double));
    memset(adj->sq_bar, 0, (size_t)(e * d) * sizeof(double));
    memset(adj->cov_bar, 0, (size_t)(d * d) * sizeof(double));
    mean_gain_adjoint(sz, &it, g, m_bar, &gr, adj);
    if (c->pairs && c->need_ops) {
        const double *sums = c->work + b * sz->p, *bars = c->sum_bar + b * sz->p;
        if (c->fused) /* G_A, G_B from the forward, times S̄ */
            pairs_adjoint(sz, &it, g, sums, bars, c->ops + b * sz->p * block, c->ops + (count + b * sz->p) * block,
                          bars, &gr, adj);
        else /* the recomputed adjoints, S̄ included */
            pairs_adjoint(sz, &it, g, sums, bars, c->ga + b * sz->p * block, c->gb + b * sz->p * block, c->ones, &gr,
                          adj);
    }
    /* ν = x − μ; c² chains into c */
    for (int64_t i = 0; i < n; ++i)
        for (int64_t k = 0; k < d; ++k) {
            const double bar = adj->nu_bar[i * d + k];
            if (gr.inputs)
                gr.inputs[i * d + k] += bar;
            if (gr.mean)
                gr.mean[k] -= bar;
        }
    if (gr.inv_ls)
        for (int64_t a = 0; a < e; ++a)
            for (int64_t k = 0; k < d; ++k)
                gr.inv_ls[a * d + k] += adj->c_bar[a * d + k] + 2.0 * it.inv_ls[a * d + k] * adj->sq_bar[a * d + k];
    if (gr.cov)
        for (int64_t i = 0; i < d * d; ++i)
            gr.cov[i] += adj->cov_bar[i];
    return STATUS_OK;
}

/* item_adjoint of every item on `workers` threads, each with its own scratch (the items' memory disjoint);
 * returns the first failing item's status, or STATUS_OK. */
static int parallel_adjoints(const struct backward_ctx *c, int workers)
{
    const int64_t items = c->sz->items;
    struct adjoint_scratch *scratch = calloc((size_t)workers, sizeof(*scratch));
    int *statuses = calloc((size_t)(items > 0 ? items : 1), sizeof(int));
    int status = scratch && statuses ? STATUS_OK : STATUS_NO_MEMORY;
    int made = 0;
    for (; made < workers && status == STATUS_OK; ++made)
        status = alloc_adjoint_scratch(scratch + made, c->sz);
    if (status == STATUS_OK) {
#pragma omp parallel for num_threads(workers) schedule(static)
        for (int64_t b = 0; b < items; ++b)
            statuses[b] = item_adjoint(c, b, scratch + omp_get_thread_num());
        for (int64_t b = 0; b < items && status == STATUS_OK; ++b)
            status = statuses[b];
    } else if (made > 0)
        --made; /* the failed one freed itself */
    for (int w = 0; w < made; ++w)
        free_adjoint_scratch(scratch + w);
    free(statuses);
    free(scratch);
    return status;
}

/* grad_out: the gradients of mean, cov, gain (NULL: none), with strides as read_output_grads reads
 * them; grad: the 7 operands' gradient buffers (NULL: not wanted; zeroed by the caller, contiguous
 * in their trailing dimensions) with batch strides `7 x ndim`; work: the forward's (sums, means),
 * failed: the forward's flags (or NULL: none failed), fused: whether work holds G_A and G_B (else
 * they, and W̄, are recomputed). Returns 0, 1 when memory is short, 2 when a B_a or R_p of an item
 * not flagged failed is not positive definite. */
int qtl_se_moments_backward(const double *const *operand, int64_t ndim, const int64_t *batch, const int64_t *strides,
                            int64_t n, int64_t d, int64_t e, const double *work, const unsigned char *failed, int fused,
                            const double *const *grad_out, const int64_t *grad_out_strides, double *const *grad,
                            const int64_t *grad_strides, int threads)
{
    int64_t items = 1;
    for (int64_t dim = 0; dim < ndim; ++dim)
        items *= batch[dim];
    const struct sizes sz = {.items = items, .n = n, .d = d, .e = e, .p = e * (e + 1) / 2, .k = d + 2};
    const int64_t count = items * sz.p, block = n * sz.k, nn = n * n;
    const int need_ops = grad[MEAN] || grad[COV] || grad[INPUTS] || grad[INV_LS] || grad[LOG_SF2];
    const double *out_mean = work + count, *ops = out_mean + items * e;
    /* the pairs matter only with a gradient of cov; without G_A, G_B from the forward, recompute */
    const int pairs = grad_out[GRAD_COV] && (need_ops || grad[WEIGHTS]);
    const int recompute = pairs && !fused;
    struct geometry g;
    if (alloc_geometry(&g, &sz))
        return STATUS_NO_MEMORY;
    struct adjoint adj = {
        .nu_bar = alloc_doubles(n * d),
        .c_bar = alloc_doubles(e * d),
        .sq_bar = alloc_doubles(e * d),
        .mat_bar = alloc_doubles(d * d),
        .tmp = alloc_doubles(2 * d * d),
        .cov_bar = alloc_doubles(d * d),
        .vec = alloc_doubles(vec_len(d)),
    };
    int64_t *offsets = all_offsets(OPERANDS, items, ndim, batch, strides);
    int64_t *grad_off = all_offsets(OPERANDS, items, ndim, batch, grad_strides);
    int64_t *sum_off = offsets ? sum_offsets(&sz, offsets + WEIGHTS * items) : NULL;
    double *sum_bar = alloc_doubles(count), *ones = alloc_doubles(sz.p);
    double *dense = alloc_doubles(2 * e + e * e + d * e);
    double *lhs = recompute ? alloc_doubles(count * block) : NULL, *rhs = recompute ? alloc_doubles(count * block) : NULL;
    double *ga = recompute && need_ops ? alloc_doubles(count * block) : NULL;
    double *gb = recompute && need_ops ? alloc_doubles(count * block) : NULL;
    int status = (!adj.nu_bar || !adj.c_bar || !adj.sq_bar || !adj.mat_bar || !adj.tmp || !adj.cov_bar || !adj.vec ||
                  !offsets || !grad_off || !sum_off || !sum_bar || !ones || !dense ||
                  (recompute && (!lhs || !rhs || (need_ops && (!ga || !gb)))))
                     ? STATUS_NO_MEMORY
                     : STATUS_OK;
    double *const g_mean = dense, *const g_cov = dense + e, *const g_gain = g_cov + e * e;
    for (int64_t p = 0; p < sz.p && status == STATUS_OK; ++p)
        ones[p] = 1.0;

    /* The recomputing path: every item's operands and S̄, then the exp sums' adjoints at once. */
    double *w_bar = NULL; /* W̄ of broadcast weights, dense per item, before it is summed */
    for (int64_t b = 0; recompute && b < items && status == STATUS_OK; ++b) {
        if (failed && failed[b]) { /* zero operands and S̄: its exp sums' adjoints are zero (poisoned below) */
            memset(lhs + b * sz.p * block, 0, (size_t)(sz.p * block) * sizeof(double));
            memset(rhs + b * sz.p * block, 0, (size_t)(sz.p * block) * sizeof(double));
            memset(sum_bar + b * sz.p, 0, (size_t)sz.p * sizeof(double));
            continue;
        }
        const struct item it = item_at(operand, offsets, items, b);
        status = item_geometry(&sz, &it, &g);
        if (status == STATUS_OK) {
            read_output_grads(grad_out, grad_out_strides, ndim, batch, b, d, e, g_mean, g_cov, g_gain);
            sum_grads(&sz, &g, g_cov, sum_bar + b * sz.p);
            item_operands(&sz, &it, &g, lhs + b * sz.p * block, rhs + b * sz.p * block, adj.vec);
        }
    }
    if (recompute && status == STATUS_OK) {
        int w_dense = grad[WEIGHTS] != NULL; /* W̄ straight into its buffer when W is not broadcast */
        for (int64_t b = 0; b < items && w_dense; ++b)
            w_dense = grad_off[WEIGHTS * items + b] == b * sz.p * nn;
        double *w_out = grad[WEIGHTS] ? (w_dense ? grad[WEIGHTS] : (w_bar = alloc_doubles(count * nn))) : NULL;
        if (grad[WEIGHTS] && !w_out)
            status = STATUS_NO_MEMORY;
        else if (qtl_exp_sum_backward(lhs, rhs, operand[WEIGHTS], sum_off, sum_off, sum_off + count,
                                      sum_off + 2 * count, count, n, n, sz.k, sum_bar, ga, gb, w_out, threads))
            status = STATUS_NO_MEMORY;
        else if (w_bar)
            for (int64_t b = 0; b < items; ++b) {
                double *dst = grad[WEIGHTS] + grad_off[WEIGHTS * items + b];
                const double *src = w_bar + b * sz.p * nn;
                for (int64_t i = 0; i < sz.p * nn; ++i)
                    dst[i] += src[i];
            }
    }

    /* The adjoint, item after item (broadcast operands' gradients summed in item order); in parallel over the
     * items when no two items add into the same gradient memory (each item's arithmetic is the same either way). */
    if (status == STATUS_OK && (need_ops || grad[BETA] || (pairs && grad[WEIGHTS]))) {
        const struct backward_ctx ctx = {
            .sz = &sz, .operand = operand, .offsets = offsets, .grad = grad, .grad_off = grad_off, .failed = failed,
            .pairs = pairs, .need_ops = need_ops, .fused = fused, .grad_out = grad_out,
            .grad_out_strides = grad_out_strides, .ndim = ndim, .batch = batch, .sum_bar = sum_bar, .work = work,
            .out_mean = out_mean, .ops = ops, .ga = ga, .gb = gb, .ones = ones,
        };
        const int workers = threads < items ? threads : (int)items;
        if (workers > 1 && disjoint_items(&sz, grad, grad_off, pairs))
            status = parallel_adjoints(&ctx, workers);
        else {
            struct adjoint_scratch serial = {.g = g, .adj = adj, .dense = dense};
            for (int64_t b = 0; b < items && status == STATUS_OK; ++b)
                status = item_adjoint(&ctx, b, &serial);
        }
    }
    free(w_bar);
    free(gb);
    free(ga);
    free(rhs);
    free(lhs);
    free(dense);
    free(ones);
    free(sum_bar);
    free(sum_off);
    free(grad_off);
    free(offsets);
    free(adj.vec);
    free(adj.cov_bar);
    free(adj.tmp);
    free(adj.mat_bar);
    free(adj.sq_bar);
    free(adj.c_bar);
    free(adj.nu_bar);
    free_geometry(&g);
    return status;
}
