/* The library's searches of one state, rule for rule as firhc_jax/_src/search: the sorted depth-first search
(sdfs.py) popping FJ_K nodes an iteration, the same stack of one batch a depth, the same pops (cheapest key,
lowest index among equals), the same incumbent rule, the same node budget with its seeds and rollouts; one
decision's work pool of FJ_LANES slots (pool.py, FJ_LANES > 0); the exhaustive searches (exhaustive.py:
FJ_EXHAUSTIVE, and per problem fj_problem's `exhaustive`: every node in the order of the level search, or the
sDFS with pruning off), so that costs, sequences and node counts agree with the library's. Sizes: FJ_N, FJ_M,
FJ_NX, FJ_NU and the solver's FJ_K, FJ_LANES and FJ_EXHAUSTIVE, set by the generated code that includes this
template (the exhaustive searches are compiled only where they run: a branch to them kept GCC from specialising
the sDFS for its problem, 1.15x slower). */

#define FJ_NEGATIVE 1
#define FJ_NONFINITE 2
#define FJ_OVERFLOW 4
#define FJ_INT32_MAX 2147483647LL
#define FJ_L (FJ_K * FJ_M)
#define FJ_STACKS (FJ_LANES > 0 ? FJ_LANES : 1)
#if defined(__GNUC__)  /* the search loop's steps inlined into it: GCC leaves them calls (1.2x slower) */
#define FJ_STEP static inline __attribute__((always_inline))
#else
#define FJ_STEP static inline
#endif

typedef struct {
    void (*children)(const double *x, int32_t k, const fj_params *p, double *xs, double *stage,
                     unsigned char *allowed);  /* every input's child */
    void (*child)(const double *x, int input, int32_t k, const fj_params *p, double *x_next, double *stage,
                  unsigned char *allowed);  /* one input's */
    unsigned char (*terminal)(const double *x, const fj_params *p);        /* NULL: no terminal set */
    double (*terminal_cost)(const double *x, const fj_params *p);          /* NULL: none */
    double (*lower_bound)(const double *x, int32_t steps_left, const fj_params *p);  /* NULL: none */
    int constrained;  /* the problem has a constraint: discarded children raise no flag */
    int exhaustive;   /* the exhaustive solver's search (generated without a lower bound): 0 none (the sDFS or
                         the pool), 1 the level search's (fj_levels), 2 the sDFS with pruning off */
    int level_iterations;  /* 1: the level search's batched calls, reported as its iterations */
} fj_problem;

typedef struct {
    double cost;        /* +inf: none yet */
    int32_t path[FJ_N];
    long long nodes;
    long long iterations;
    int flags;
} fj_incumbent;

typedef struct {  /* the children of one parent */
    double x[FJ_M][FJ_NX];
    double cost[FJ_M];
    double key[FJ_M];
    unsigned char bad[FJ_M];
    int flags[FJ_M];
    unsigned char terminal_ok[FJ_M];
} fj_children;

typedef struct {  /* stack.py's Stack: one batch of FJ_L nodes a depth */
    double x[FJ_N + 1][FJ_L][FJ_NX];
    double cost[FJ_N + 1][FJ_L];
    double key[FJ_N + 1][FJ_L];
    double low[FJ_N + 1];
    int32_t parents[FJ_N + 1][FJ_K][FJ_N];
} fj_stack;

typedef struct {
    fj_stack st[FJ_STACKS];
    fj_children ch[FJ_K];  /* of the FJ_K nodes expanded together */
} fj_work;

typedef struct {  /* stack.py's Popped: nodes taken out of one row, cheapest first (+inf keys: none) */
    double x[FJ_K][FJ_NX];
    double cost[FJ_K];
    double key[FJ_K];
    int32_t path[FJ_K][FJ_N];
} fj_popped;

/* @functions: the generated callables go above this line */

/* Whether every entry is finite: v * 0 is 0 for a finite v and NaN for an infinite or NaN one (one branch-free
   pass; the code must not be compiled with -ffast-math, which would fold it away). */
static int fj_all_finite(const double *v, int n) {
    double zero = 0.0;
    for (int i = 0; i < n; i++) zero += v[i] * 0.0;
    return zero == 0.0;
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
            double bound = P->lower_bound(ch->x[i], (int32_t)steps_left, p);
            key = c + (isnan(bound) ? 0.0 : bound);
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

/* nodes.tally of one expanded parent: its FJ_M children and their error flags. */
FJ_STEP void fj_count(fj_incumbent *s, const fj_children *ch) {
    s->nodes += FJ_M;
    for (int i = 0; i < FJ_M; i++) s->flags |= ch->flags[i];
}

/* stack.init: the root x0 alone, at row 0. */
static void fj_stack_init(fj_stack *st, const double *x0) {
    for (int r = 0; r <= FJ_N; r++) {
        for (int i = 0; i < FJ_L; i++) st->key[r][i] = INFINITY;
        for (int b = 0; b < FJ_K; b++) for (int j = 0; j < FJ_N; j++) st->parents[r][b][j] = -1;
        st->low[r] = INFINITY;
    }
    for (int j = 0; j < FJ_NX; j++) st->x[0][0][j] = x0[j];
    st->cost[0][0] = 0.0;
    st->key[0][0] = 0.0;
    st->low[0] = 0.0;
}

/* stack.top: the deepest row with a key below `bound`; -1 if none. */
FJ_STEP int fj_top(const fj_stack *st, double bound) {
    for (int r = FJ_N; r >= 0; r--) if (st->low[r] < bound) return r;
    return -1;
}

/* stack.pop: the k cheapest remaining nodes of `row` into pp from entry `at` (a row outside the stack takes none:
   +inf keys). */
FJ_STEP void fj_pop(fj_stack *st, int row, int k, fj_popped *pp, int at) {
    if (row < 0 || row > FJ_N) {
        for (int b = at; b < at + k; b++) pp->key[b] = INFINITY;
        return;
    }
    for (int b = at; b < at + k; b++) {
        double low;
        int i = fj_first_min_key(st->key[row], FJ_L, &low);
        pp->key[b] = low;
        pp->cost[b] = st->cost[row][i];
        for (int j = 0; j < FJ_NX; j++) pp->x[b][j] = st->x[row][i][j];
        for (int j = 0; j < FJ_N; j++) pp->path[b][j] = (j == row - 1) ? i % FJ_M : st->parents[row][i / FJ_M][j];
        st->key[row][i] = INFINITY;
    }
    double rest = INFINITY;
    for (int i = 0; i < FJ_L; i++) rest = st->key[row][i] < rest ? st->key[row][i] : rest;
    st->low[row] = rest;
}

/* sdfs.settle_children and the push, for the nodes pp popped from `row` of st: the children of those whose key
   is below `incumbent` (all with prune 0) computed and counted into *stats, the cheapest usable feasible leaf
   (*leaf_cost, leaf_path: the return value says whether it is strictly cheaper than `incumbent`), the other
   children pushed at row + 1. `leaf_depth` < FJ_N and `full` non-NULL: a seed level (sdfs.seed's leaves: the
   full problem's terminal cost at the leaves, and its bound's +inf discards). */
FJ_STEP int fj_settle(const fj_problem *P, const fj_params *p, fj_stack *st, const fj_popped *pp, int row,
                     double incumbent, int prune, int leaf_depth, const fj_problem *full, fj_children *ch,
                     fj_incumbent *stats, double *leaf_cost, int32_t *leaf_path) {
    const double inf = INFINITY;
    int depth = row + 1;
    double bound = prune ? incumbent : inf;
    for (int b = 0; b < FJ_K; b++) {
        fj_children *c = &ch[b];
        if (!(pp->key[b] < bound)) {  /* computed by XLA, never used: not here */
            for (int j = 0; j < FJ_M; j++) c->bad[j] = 1;
            continue;
        }
        fj_expand(P, p, pp->x[b], pp->cost[b], FJ_N - depth, c);
        fj_count(stats, c);
        if (full) {
            for (int j = 0; j < FJ_M; j++) {
                if (full->lower_bound && full->lower_bound(c->x[j], (int32_t)(FJ_N - depth), p) == inf)
                    c->bad[j] = 1;
                if (depth == leaf_depth && full->terminal_cost) {
                    double extra = full->terminal_cost(c->x[j], p);
                    c->cost[j] = c->cost[j] + extra;
                    c->key[j] = c->key[j] + extra;
                }
            }
        }
    }
    stats->iterations += 1;
    double low = inf;
    *leaf_cost = inf;
    int improve = 0;
    if (depth == leaf_depth) {
        double leaf[FJ_L];
        for (int b = 0; b < FJ_K; b++)
            for (int j = 0; j < FJ_M; j++)
                leaf[b * FJ_M + j] = (!ch[b].bad[j] && ch[b].terminal_ok[j]) ? ch[b].cost[j] : inf;
        int i = fj_first_min_key(leaf, FJ_L, leaf_cost);
        improve = *leaf_cost < incumbent;
        for (int j = 0; j < FJ_N; j++) leaf_path[j] = (j == row) ? i % FJ_M : pp->path[i / FJ_M][j];
        for (int i = 0; i < FJ_L; i++) st->key[depth][i] = inf;
    } else {
        for (int b = 0; b < FJ_K; b++) {
            const fj_children *c = &ch[b];
            for (int j = 0; j < FJ_M; j++) {
                int i = b * FJ_M + j;
                int keep = !c->bad[j] && c->key[j] < bound;
                double key = keep ? c->key[j] : inf;
                st->key[depth][i] = key;
                low = key < low ? key : low;
                if (keep) {
                    st->cost[depth][i] = c->cost[j];
                    for (int d = 0; d < FJ_NX; d++) st->x[depth][i][d] = c->x[j][d];
                }
            }
            for (int j = 0; j < FJ_N; j++) st->parents[depth][b][j] = pp->path[b][j];
        }
    }
    st->low[depth] = low;
    return improve;
}

/* sdfs._dfs: the sorted DFS from x0 with the first incumbent *inc, while the node count stays at most `limit`
   before an iteration (limit - reserve while there is no incumbent); prune 0: the whole tree. `leaf_depth` and
   `full` as fj_settle's. Returns whether the search ran to the end. */
static int fj_dfs(const fj_problem *P, const fj_params *p, const double *x0, fj_incumbent *inc, long long limit,
                  long long reserve, int leaf_depth, const fj_problem *full, int prune, fj_work *w) {
    fj_stack *st = &w->st[0];
    fj_popped pp;
    double leaf_cost;
    int32_t leaf_path[FJ_N];
    fj_stack_init(st, x0);
    int row = fj_top(st, prune ? inc->cost : INFINITY);
    fj_pop(st, row, FJ_K, &pp, 0);
    while (row >= 0 && inc->nodes <= limit - (inc->cost < INFINITY ? 0 : reserve)) {
        if (fj_settle(P, p, st, &pp, row, inc->cost, prune, leaf_depth, full, w->ch, inc, &leaf_cost, leaf_path)) {
            inc->cost = leaf_cost;
            for (int j = 0; j < FJ_N; j++) inc->path[j] = leaf_path[j];
        }
        row = fj_top(st, prune ? inc->cost : INFINITY);
        fj_pop(st, row, FJ_K, &pp, 0);
    }
    return row < 0;
}

static void fj_none(fj_incumbent *s) {
    s->cost = INFINITY;
    for (int j = 0; j < FJ_N; j++) s->path[j] = -1;
    s->nodes = 0;
    s->iterations = 0;
    s->flags = 0;
}

#if !FJ_EXHAUSTIVE
/* The first index of the smallest entry (index 0 when every entry is +inf, as jnp's two reductions give). */
static int fj_first_min(const double *a, int n, double *low) {
    double m = a[0];
    for (int i = 1; i < n; i++) m = FJ_MIN(m, a[i]);
    int first = n;
    for (int i = 0; i < n; i++) if (a[i] == m) { first = i; break; }
    *low = m;
    return first < n - 1 ? first : n - 1;
}

static void fj_tally(fj_incumbent *s, const fj_children *ch) {
    fj_count(s, ch);
    s->iterations += 1;
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
            fj_children *ch = &w->ch[0];
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
    long long share = max_nodes / 2, L = FJ_L;
    int done = 1;
    for (int D = 1; done && D < FJ_N && best->nodes <= share - FJ_N * FJ_M - L && share >= FJ_M + FJ_N * FJ_M + L;
         D++) {
        fj_incumbent found;
        fj_none(&found);
        found.nodes = best->nodes;
        found.iterations = best->iterations;
        found.flags = best->flags;
        done = fj_dfs(&level, p, x0, &found, share - FJ_N * FJ_M - L, 0, D, P, 1, w);
        best->nodes = found.nodes;
        best->iterations = found.iterations;
        best->flags = found.flags;
        if (found.cost < INFINITY && found.nodes + FJ_N * FJ_M <= max_nodes)
            fj_rollout(P, p, x0, found.path, D, best, w);
    }
}

#else
/* exhaustive._exhaustive: every node below a usable one, the leaves in the lexicographic order of their
   sequences, the first of the cheapest kept; iterations as the level search counts its batched calls. */
static void fj_levels(const fj_problem *P, const fj_params *p, const double *x0, fj_incumbent *out, fj_work *w) {
    fj_stack *st = &w->st[0];  /* row d: the children of the node of depth d - 1 on the current path */
    fj_children *ch = &w->ch[0];
    unsigned char usable[FJ_N + 1][FJ_M];
    int next[FJ_N + 1];
    int32_t path[FJ_N];
    const double *x = x0;
    double cost = 0.0;
    int r = 0;  /* depth of the node expanded next */
    for (;;) {
        fj_expand(P, p, x, cost, FJ_N - 1 - r, ch);
        fj_count(out, ch);
        if (r + 1 == FJ_N) {
            for (int i = 0; i < FJ_M; i++)
                if (!ch->bad[i] && ch->terminal_ok[i] && ch->cost[i] < out->cost) {
                    out->cost = ch->cost[i];
                    for (int j = 0; j < FJ_N - 1; j++) out->path[j] = path[j];
                    out->path[FJ_N - 1] = i;
                }
        } else {
            r += 1;
            for (int i = 0; i < FJ_M; i++) {
                usable[r][i] = !ch->bad[i];
                st->cost[r][i] = ch->cost[i];
                for (int j = 0; j < FJ_NX; j++) st->x[r][i][j] = ch->x[i][j];
            }
            next[r] = 0;
        }
        int i = FJ_M;
        while (r > 0) {  /* the next usable node in the lexicographic order */
            i = next[r];
            while (i < FJ_M && !usable[r][i]) i++;
            if (i < FJ_M) break;
            r -= 1;
        }
        if (r == 0) break;
        next[r] = i + 1;
        path[r - 1] = i;
        x = st->x[r][i];
        cost = st->cost[r][i];
    }
    out->iterations = P->level_iterations;
}
#endif

#if FJ_LANES > 0
/* pool._pool_one: one decision on the work pool (pool.pool_search of one row) of FJ_LANES slots, each an sDFS
   stack; a free slot steals the next node of the shallowest live batch below a busy slot's deepest one. Every
   slot settles its nodes against the incumbent of the iteration's start; the cheapest improving leaf is kept (the
   last slot's among equal ones). Returns whether no slot was stopped by the budget. */
static int fj_pool(const fj_problem *P, const fj_params *p, const double *x0, fj_incumbent *out,
                   long long max_nodes, long long reserve, fj_work *w) {
    enum { S = FJ_LANES };
    const double inf = INFINITY;
    fj_popped work[S], given[S];
    int row[S], depth[S], head = 0;  /* row 1: none yet */
    long long cut = max_nodes < FJ_L;
    double leaf_cost[S];
    int32_t leaf_path[S][FJ_N];
    for (int s = 0; s < S; s++) {
        fj_stack_init(&w->st[s], x0);
        for (int r = 0; r <= FJ_N; r++) w->st[s].low[r] = inf;
        w->st[s].key[0][0] = inf;
        row[s] = 1;
    }
    for (;;) {
        /* pool.plan */
        long long budget_row = max_nodes - (out->cost < inf ? 0 : reserve);
        unsigned char live[S][FJ_N + 1], busy[S];
        int top[S], free_[S], can[S], free_rank[S], can_rank[S], shallowest[S], root[S], victim[S], robbed[S];
        int by_rank[S], new_row[S], sharing0 = 0, sharing1 = 0, nfree = 0, ncan = 0;
        for (int s = 0; s < S; s++) {
            double bound = row[s] == 0 ? out->cost : inf;
            busy[s] = 0;
            for (int d = 0; d <= FJ_N; d++) busy[s] |= live[s][d] = w->st[s].low[d] < bound;
            if (busy[s] && row[s] == 0) sharing0++; else sharing1++;
        }
        for (int s = 0; s < S; s++) {
            long long nodes = row[s] == 0 ? out->nodes : 0, budget = row[s] == 0 ? budget_row : 0;
            long long sharing = row[s] == 0 ? sharing0 : sharing1;
            int spent = nodes > budget - sharing * FJ_L;
            if (spent && busy[s]) cut++;
            top[s] = -1;
            for (int d = 0; d <= FJ_N; d++) {
                live[s][d] = live[s][d] && !spent;
                if (live[s][d]) top[s] = d;
            }
            free_[s] = top[s] < 0;
            int roomy = nodes <= budget - (sharing + S) * FJ_L;
            can[s] = 0;
            shallowest[s] = 0;
            for (int d = FJ_N; d >= 0; d--) {
                if (live[s][d] && roomy && d < top[s]) { can[s] = 1; shallowest[s] = d; }  /* stealable */
            }
            free_rank[s] = nfree + free_[s] - 1;
            can_rank[s] = ncan + can[s] - 1;
            nfree += free_[s];
            ncan += can[s];
        }
        for (int s = 0; s < S; s++) by_rank[s] = 0;
        for (int s = 0; s < S; s++) if (can[s]) by_rank[can_rank[s]] = s;
        for (int s = 0; s < S; s++) {
            root[s] = free_[s] && head + free_rank[s] < 1 ? head + free_rank[s] : -1;
            if (root[s] >= 0 && out->nodes > budget_row - FJ_L) { cut++; root[s] = -1; }  /* a row never started */
            int t_rank = free_rank[s] - (1 - head);
            int steals = free_[s] && t_rank >= 0 && t_rank < ncan;
            victim[s] = steals ? by_rank[t_rank < 0 ? 0 : t_rank > S - 1 ? S - 1 : t_rank] : -1;
            robbed[s] = can[s] && can_rank[s] < nfree - (1 - head) ? shallowest[s] : -1;
        }
        for (int s = 0; s < S; s++) {
            int v = victim[s] > 0 ? victim[s] : 0;
            new_row[s] = victim[s] >= 0 ? row[v] : root[s] >= 0 ? root[s] : row[s];
            depth[s] = top[s] >= 0 ? top[s] : root[s] >= 0 ? 0 : victim[s] >= 0 ? shallowest[v] : -1;
        }
        for (int s = 0; s < S; s++) {
            if (new_row[s] != row[s]) for (int d = 0; d <= FJ_N; d++) w->st[s].low[d] = inf;
            row[s] = new_row[s];
        }
        head = head + nfree < 1 ? head + nfree : 1;
        /* pool.take */
        for (int s = 0; s < S; s++) fj_pop(&w->st[s], top[s], FJ_K, &work[s], 0);
        for (int s = 0; s < S; s++) fj_pop(&w->st[s], robbed[s], 1, &given[s], 0);
        int more = head < 1;
        for (int s = 0; s < S; s++) {
            if (root[s] >= 0) {
                for (int j = 0; j < FJ_NX; j++) work[s].x[0][j] = x0[j];
                work[s].cost[0] = 0.0;
                work[s].key[0] = 0.0;
                for (int j = 0; j < FJ_N; j++) work[s].path[0][j] = -1;
            }
            if (victim[s] >= 0) {
                const fj_popped *g = &given[victim[s]];
                for (int j = 0; j < FJ_NX; j++) work[s].x[0][j] = g->x[0][j];
                work[s].cost[0] = g->cost[0];
                work[s].key[0] = g->key[0];
                for (int j = 0; j < FJ_N; j++) work[s].path[0][j] = g->path[0][j];
            }
            more |= depth[s] >= 0;
        }
        if (!more) break;
        /* pool.expand_and_store */
        double incumbent = out->cost, best = out->cost;
        int improve[S];
        for (int s = 0; s < S; s++) {
            improve[s] = 0;
            if (depth[s] < 0) continue;  /* idle: its nodes are none */
            improve[s] = fj_settle(P, p, &w->st[s], &work[s], depth[s], row[s] == 0 ? incumbent : inf, 1, FJ_N,
                                   NULL, w->ch, out, &leaf_cost[s], leaf_path[s]);
            if (improve[s] && leaf_cost[s] < best) best = leaf_cost[s];
        }
        for (int s = 0; s < S; s++)
            if (improve[s] && leaf_cost[s] == best) {
                out->cost = best;
                for (int j = 0; j < FJ_N; j++) out->path[j] = leaf_path[s][j];
            }
    }
    return cut == 0;
}
#endif

/* The solver's search (solvers.SOLVERS[...].search): sdfs.search and pool._pool_one take the candidates (`count`
   sequences [FJ_N]; in a budgeted search a prefix then -1) and the seeds first; the exhaustive searches take
   neither, nor a budget. Returns whether it ran to the end. */
static int fj_search(const fj_problem *P, const fj_params *p, const double *x0, const int32_t *candidates,
                     int count, long long max_nodes, int budgeted, long long reserve, fj_incumbent *out,
                     fj_work *w) {
    fj_none(out);
#if FJ_EXHAUSTIVE
    (void)candidates; (void)count; (void)max_nodes; (void)budgeted; (void)reserve;
    int done = 1;
    if (P->exhaustive == 1) fj_levels(P, p, x0, out, w);
    else done = fj_dfs(P, p, x0, out, FJ_INT32_MAX - FJ_L, 0, FJ_N, NULL, 0, w);
#else
    long long own = max_nodes - reserve;
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
#if FJ_LANES > 0
    int done = fj_pool(P, p, x0, out, max_nodes, reserve, w);
#else
    int done = fj_dfs(P, p, x0, out, max_nodes - FJ_L, reserve, FJ_N, NULL, 1, w);
#endif
#endif
    if (!isfinite(out->cost))
        for (int j = 0; j < FJ_N; j++) out->path[j] = -1;
    return done;
}
