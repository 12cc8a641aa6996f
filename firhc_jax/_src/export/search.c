/* The sorted depth-first search, one node popped an iteration (pop_width = 1), rule for rule as
   firhc_jax/_src/search/sdfs.py: the same stack of one batch a depth, the same pops (cheapest key, lowest
   index among equals), the same incumbent rule, the same node budget with its seeds and rollouts, so that
   costs, sequences and node counts agree with fj.sdfs. Sizes: FJ_N, FJ_M, FJ_NX, FJ_NU, set by the generated
   code that includes this template. */

#define FJ_NEGATIVE 1
#define FJ_NONFINITE 2
#define FJ_OVERFLOW 4
#define FJ_INT32_MAX 2147483647LL

typedef struct {
    void (*children)(const double *x, int32_t k, const fj_params *p, double *xs, double *stage,
                     unsigned char *allowed);  /* every input's child */
    void (*child)(const double *x, int input, int32_t k, const fj_params *p, double *x_next, double *stage,
                  unsigned char *allowed);  /* one input's */
    unsigned char (*terminal)(const double *x, const fj_params *p);        /* NULL: no terminal set */
    double (*terminal_cost)(const double *x, const fj_params *p);          /* NULL: none */
    double (*lower_bound)(const double *x, int32_t steps_left, const fj_params *p);  /* NULL: none */
    int constrained;  /* the problem has a constraint: discarded children raise no flag */
} fj_problem;

typedef struct {
    double cost;        /* +inf: none yet */
    int32_t path[FJ_N];
    long long nodes;
    long long iterations;
    int flags;
} fj_incumbent;

typedef struct {
    double x[FJ_M][FJ_NX];
    double cost[FJ_M];
    double key[FJ_M];
    unsigned char bad[FJ_M];
    int flags[FJ_M];
    unsigned char terminal_ok[FJ_M];
} fj_children;

typedef struct {
    double x[FJ_N + 1][FJ_M][FJ_NX];
    double cost[FJ_N + 1][FJ_M];
    double key[FJ_N + 1][FJ_M];
    double low[FJ_N + 1];
    int32_t parents[FJ_N + 1][FJ_N];
    fj_children ch;
} fj_work;

/* @functions: the generated callables go above this line */

/* Whether every entry is finite: v * 0 is 0 for a finite v and NaN for an infinite or NaN one (one branch-free
   pass; the code must not be compiled with -ffast-math, which would fold it away). */
static int fj_all_finite(const double *v, int n) {
    double zero = 0.0;
    for (int i = 0; i < n; i++) zero += v[i] * 0.0;
    return zero == 0.0;
}

/* The first index of the smallest entry (index 0 when every entry is +inf, as jnp's two reductions give). */
static int fj_first_min(const double *a, int n, double *low) {
    double m = a[0];
    for (int i = 1; i < n; i++) m = FJ_MIN(m, a[i]);
    int first = n;
    for (int i = 0; i < n; i++) if (a[i] == m) { first = i; break; }
    *low = m;
    return first < n - 1 ? first : n - 1;
}

/* nodes.expand for one parent: children of x (cost so far `cost`), steps_left inputs still to come after them. */
static void fj_expand(const fj_problem *P, const fj_params *p, const double *x, double cost, int steps_left,
                      fj_children *ch) {
    double stage[FJ_M];
    unsigned char allowed[FJ_M];
    int k = FJ_N - 1 - steps_left;
    k = k < 0 ? 0 : k > FJ_N - 1 ? FJ_N - 1 : k;
    P->children(x, (int32_t)k, p, &ch->x[0][0], stage, allowed);
    for (int i = 0; i < FJ_M; i++) {
        double s = stage[i];
        if (steps_left == 0 && P->terminal_cost) s = s + P->terminal_cost(ch->x[i], p);
        double c = cost + s;
        int nonfinite = isnan(c) || !fj_all_finite(ch->x[i], FJ_NX);
        int overflow = isinf(c) && isfinite(cost) && isfinite(s);
        int flags = (s < 0) * FJ_NEGATIVE | nonfinite * FJ_NONFINITE | overflow * FJ_OVERFLOW;
        unsigned char bad = (unsigned char)nonfinite;
        if (P->constrained) {
            bad = (unsigned char)(nonfinite || !allowed[i]);
            if (!allowed[i]) flags = 0;
        }
        ch->cost[i] = c;
        ch->bad[i] = bad;
        ch->flags[i] = flags;
        ch->terminal_ok[i] = (steps_left == 0 && P->terminal) ? P->terminal(ch->x[i], p) : 1;
        double key = c;
        if (P->lower_bound && steps_left > 0) {
            double b = P->lower_bound(ch->x[i], (int32_t)steps_left, p);
            key = c + (isnan(b) ? 0.0 : b);
        }
        ch->key[i] = key;
    }
}

/* fj_first_min of keys and leaf costs, which are never NaN (a NaN cost makes a child bad, its key +inf): one
   pass of plain comparisons. */
static int fj_first_min_key(const double *a, int n, double *low) {
    double m = a[0];
    int first = 0;
    for (int i = 1; i < n; i++)
        if (a[i] < m) { m = a[i]; first = i; }
    *low = m;
    return first;
}

static void fj_tally(fj_incumbent *s, const fj_children *ch) {
    s->nodes += FJ_M;
    s->iterations += 1;
    for (int i = 0; i < FJ_M; i++) s->flags |= ch->flags[i];
}

/* sdfs._dfs: the sorted DFS from x0 with the first incumbent *inc, while the node count stays at most `limit`
   before an iteration (limit - reserve while there is no incumbent). `leaf_depth` < FJ_N and `full` non-NULL:
   a seed level (sdfs.seed's leaves: the full problem's terminal cost at the leaves, and its bound's +inf
   discards). Returns whether the search ran to the end. */
static int fj_dfs(const fj_problem *P, const fj_params *p, const double *x0, fj_incumbent *inc, long long limit,
                  long long reserve, int leaf_depth, const fj_problem *full, fj_work *w) {
    const double inf = INFINITY;
    for (int r = 0; r <= FJ_N; r++) {
        for (int i = 0; i < FJ_M; i++) w->key[r][i] = inf;
        for (int j = 0; j < FJ_N; j++) w->parents[r][j] = -1;
        w->low[r] = inf;
    }
    for (int j = 0; j < FJ_NX; j++) w->x[0][0][j] = x0[j];
    w->cost[0][0] = 0.0;
    w->key[0][0] = 0.0;
    w->low[0] = 0.0;
    double px[FJ_NX], pcost = 0.0, pkey = inf;
    int32_t ppath[FJ_N];
    int row;
#define FJ_NEXT_NODES()                                                                             \
    do {                                                                                            \
        row = -1;                                                                                   \
        for (int r = FJ_N; r >= 0; r--) if (w->low[r] < inc->cost) { row = r; break; }              \
        if (row >= 0) {                                                                             \
            double low;                                                                             \
            int i = fj_first_min_key(w->key[row], FJ_M, &low);                                      \
            pkey = low;                                                                             \
            pcost = w->cost[row][i];                                                                \
            for (int j = 0; j < FJ_NX; j++) px[j] = w->x[row][i][j];                                \
            for (int j = 0; j < FJ_N; j++) ppath[j] = (j == row - 1) ? i : w->parents[row][j];      \
            w->key[row][i] = inf;                                                                   \
            double rest = inf;                                                                      \
            for (int j = 0; j < FJ_M; j++) rest = w->key[row][j] < rest ? w->key[row][j] : rest;    \
            w->low[row] = rest;                                                                     \
        }                                                                                           \
    } while (0)
    FJ_NEXT_NODES();
    while (row >= 0 && inc->nodes <= limit - (inc->cost < inf ? 0 : reserve)) {
        fj_children *ch = &w->ch;
        int depth = row + 1;
        fj_expand(P, p, px, pcost, FJ_N - depth, ch);
        if (full) {
            for (int i = 0; i < FJ_M; i++) {
                if (full->lower_bound && full->lower_bound(ch->x[i], (int32_t)(FJ_N - depth), p) == inf)
                    ch->bad[i] = 1;
                if (depth == leaf_depth && full->terminal_cost) {
                    double extra = full->terminal_cost(ch->x[i], p);
                    ch->cost[i] = ch->cost[i] + extra;
                    ch->key[i] = ch->key[i] + extra;
                }
            }
        }
        int alive = pkey < inc->cost;
        double bound = inc->cost;
        double leaf[FJ_M], leaf_cost = inf;
        int leaf_i = 0;
        if (depth == leaf_depth) {
            for (int i = 0; i < FJ_M; i++)
                leaf[i] = (alive && !ch->bad[i] && ch->terminal_ok[i]) ? ch->cost[i] : inf;
            leaf_i = fj_first_min_key(leaf, FJ_M, &leaf_cost);
        }
        int improve = leaf_cost < inc->cost;
        if (improve) bound = leaf_cost;
        if (alive) fj_tally(inc, ch); else inc->iterations += 1;
        if (improve) {
            inc->cost = leaf_cost;
            for (int j = 0; j < FJ_N; j++) inc->path[j] = (j == row) ? leaf_i : ppath[j];
        }
        double low = inf;
        if (depth < leaf_depth) {
            for (int i = 0; i < FJ_M; i++) {
                int keep = alive && !ch->bad[i] && ch->key[i] < bound;
                double key = keep ? ch->key[i] : inf;
                w->key[depth][i] = key;
                low = key < low ? key : low;
                if (keep) {
                    w->cost[depth][i] = ch->cost[i];
                    for (int j = 0; j < FJ_NX; j++) w->x[depth][i][j] = ch->x[i][j];
                }
            }
            for (int j = 0; j < FJ_N; j++) w->parents[depth][j] = ppath[j];
        } else {
            for (int i = 0; i < FJ_M; i++) w->key[depth][i] = inf;
        }
        w->low[depth] = low;
        FJ_NEXT_NODES();
    }
#undef FJ_NEXT_NODES
    return row < 0;
}

/* One step of a given input from x at step k, as nodes.rollout_cost and the rollout's replay take it: the
   child x_next, whether the constraint holds, the error flags the step raises, and the cost so far plus the
   stage cost (and at the last step the terminal cost). */
static double fj_given_step(const fj_problem *P, const fj_params *p, const double *x, int input, int k,
                            double cost, double *x_next, unsigned char *allowed, int *flags) {
    double s;
    P->child(x, input, (int32_t)k, p, x_next, &s, allowed);
    if (k == FJ_N - 1 && P->terminal_cost) s = s + P->terminal_cost(x_next, p);
    double total = cost + s;
    int nonfinite = isnan(total) || !fj_all_finite(x_next, FJ_NX);
    int overflow = isinf(total) && isfinite(cost) && isfinite(s);
    *flags = (s < 0) * FJ_NEGATIVE | nonfinite * FJ_NONFINITE | overflow * FJ_OVERFLOW;
    return total;
}

/* sdfs._rollout: prefix[:length] replayed, then extended by the greedy rule; the cheaper of *start and it. */
static void fj_rollout(const fj_problem *P, const fj_params *p, const double *x0, const int32_t *prefix,
                       int length, fj_incumbent *start, fj_work *w) {
    double x[FJ_NX], cost = 0.0;
    int ok = 1;
    int32_t path[FJ_N];
    for (int j = 0; j < FJ_NX; j++) x[j] = x0[j];
    for (int k = 0; k < FJ_N; k++) {
        if (k < length) {
            double xs[FJ_NX];
            unsigned char allowed;
            int flags;
            double total = fj_given_step(P, p, x, prefix[k], k, cost, xs, &allowed, &flags);
            int met = ok && allowed;
            start->nodes += 1;
            if (met) start->flags |= flags;
            for (int j = 0; j < FJ_NX; j++) x[j] = xs[j];
            cost = total;
            ok = met && !(flags & FJ_NONFINITE);
            path[k] = prefix[k];
        } else {
            fj_children *ch = &w->ch;
            fj_expand(P, p, x, cost, FJ_N - 1 - k, ch);
            double score[FJ_M], low;
            for (int i = 0; i < FJ_M; i++) {
                int usable = !ch->bad[i] && (k < FJ_N - 1 || ch->terminal_ok[i]);
                double key = usable ? ch->key[i] : INFINITY;
                score[i] = key;
                if (P->terminal_cost && k < FJ_N - 1) score[i] = key + P->terminal_cost(ch->x[i], p);
            }
            int i = fj_first_min(score, FJ_M, &low);
            int usable = !ch->bad[i] && (k < FJ_N - 1 || ch->terminal_ok[i]);
            ok = ok && isfinite(usable ? ch->key[i] : INFINITY);
            for (int j = 0; j < FJ_NX; j++) x[j] = ch->x[i][j];
            cost = ch->cost[i];
            path[k] = i;
            fj_tally(start, ch);
        }
    }
    if (P->terminal) ok = ok && (length < FJ_N || P->terminal(x, p));
    if (!ok) cost = INFINITY;
    if (cost < start->cost) {
        start->cost = cost;
        for (int j = 0; j < FJ_N; j++) start->path[j] = path[j];
    }
}

static void fj_none(fj_incumbent *s) {
    s->cost = INFINITY;
    for (int j = 0; j < FJ_N; j++) s->path[j] = -1;
    s->nodes = 0;
    s->iterations = 0;
    s->flags = 0;
}

/* nodes.rollout_cost of a whole sequence, as sdfs.start_incumbent evaluates an unbudgeted candidate. */
static void fj_candidate(const fj_problem *P, const fj_params *p, const double *x0, const int32_t *seq,
                         long long max_nodes, fj_incumbent *start) {
    for (int k = 0; k < FJ_N; k++) if (seq[k] < 0 || seq[k] >= FJ_M) return;
    if (start->nodes + FJ_N > max_nodes) return;
    double x[FJ_NX], cost = 0.0;
    int flags = 0, met = 1;
    for (int j = 0; j < FJ_NX; j++) x[j] = x0[j];
    for (int k = 0; k < FJ_N; k++) {
        double xn[FJ_NX];
        unsigned char allowed;
        int step_flags;
        double c = fj_given_step(P, p, x, seq[k], k, cost, xn, &allowed, &step_flags);
        if (met && allowed) flags |= step_flags;
        met = met && allowed;
        for (int j = 0; j < FJ_NX; j++) x[j] = xn[j];
        cost = c;
    }
    int ok = met && !(flags & FJ_NONFINITE) && (!P->terminal || P->terminal(x, p));
    if (!ok) cost = INFINITY;
    start->nodes += FJ_N;
    start->flags |= flags;
    if (cost < start->cost) {
        start->cost = cost;
        for (int j = 0; j < FJ_N; j++) start->path[j] = seq[j];
    }
}

/* sdfs.seed: first incumbents by iterative deepening within half the budget. */
static void fj_seed(const fj_problem *P, const fj_params *p, const double *x0, fj_incumbent *best,
                    long long max_nodes, fj_work *w) {
    fj_problem level = *P;
    level.terminal = NULL;
    level.terminal_cost = NULL;
    level.lower_bound = NULL;
    long long share = max_nodes / 2, L = FJ_M;
    int done = 1;
    for (int D = 1; done && D < FJ_N && best->nodes <= share - FJ_N * FJ_M - L && share >= FJ_M + FJ_N * FJ_M + L;
         D++) {
        fj_incumbent found;
        fj_none(&found);
        found.nodes = best->nodes;
        found.iterations = best->iterations;
        found.flags = best->flags;
        done = fj_dfs(&level, p, x0, &found, share - FJ_N * FJ_M - L, 0, D, P, w);
        best->nodes = found.nodes;
        best->iterations = found.iterations;
        best->flags = found.flags;
        if (found.cost < INFINITY && found.nodes + FJ_N * FJ_M <= max_nodes)
            fj_rollout(P, p, x0, found.path, D, best, w);
    }
}

/* sdfs.search: the candidates (`count` sequences [FJ_N]; in a budgeted search a prefix then -1), the seeds, the
   search. Returns whether it ran to the end. */
static int fj_search(const fj_problem *P, const fj_params *p, const double *x0, const int32_t *candidates,
                     int count, long long max_nodes, int budgeted, long long reserve, fj_incumbent *out,
                     fj_work *w) {
    long long own = max_nodes - reserve;
    fj_none(out);
    for (int c = 0; c < count; c++) {
        const int32_t *seq = candidates + c * FJ_N;
        if (!budgeted) {
            fj_candidate(P, p, x0, seq, own, out);
            continue;
        }
        int k = 0;
        while (k < FJ_N && seq[k] >= 0) k++;
        if (k > 0 && out->nodes + k + (long long)(FJ_N - k) * FJ_M <= own) fj_rollout(P, p, x0, seq, k, out, w);
    }
    if (budgeted) fj_seed(P, p, x0, out, own, w);
    int done = fj_dfs(P, p, x0, out, max_nodes - FJ_M, reserve, FJ_N, NULL, w);
    if (!isfinite(out->cost))
        for (int j = 0; j < FJ_N; j++) out->path[j] = -1;
    return done;
}
