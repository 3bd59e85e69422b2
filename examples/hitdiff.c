/*
** examples/hitdiff.c -- compare two hit files ray by ray, e.g. batchrt's
** against an Embree build's, and print an agreement table.
**
**   build/hitdiff A.hits B.hits [--max-disagree FRACTION] [--t-rel TOL]
**
** A ray agrees when both files miss it, or both hit the same triangle at
** distances whose relative difference |tA - tB| / max(|tA|, |tB|) is at
** most --t-rel.  Barycentrics are reported but never judged: two correct
** watertight tests may round them differently.
**
** Exit status: 0 when the fraction of rays that disagree is at most
** --max-disagree, 1 when it is larger (or on bad input), 2 when the files
** hold different numbers of records (they cannot describe the same rays).
*/
#include "common.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *const prog = "hitdiff";

typedef struct agreement {
    uint64_t rays;
    uint64_t both_miss;
    uint64_t same_prim;
    uint64_t different_prim;      /* both hit, different triangles */
    uint64_t a_only, b_only;      /* hit in one file, miss in the other */
    uint64_t t_over;              /* same prim, relative t difference > t_rel */
    double t_max, t_sum;          /* relative t difference over same prim */
    double uv_max;                /* largest |du| or |dv| over same prim */
} agreement;

static void usage(void)
{
    printf("usage: build/hitdiff A.hits B.hits [--max-disagree FRACTION] [--t-rel TOL]\n"
           "Compares two hit files (16-byte records) ray by ray and prints a table.\n"
           "\n"
           "  --max-disagree F  largest tolerated fraction of disagreeing rays, 0..1\n"
           "                    (default 0: every ray must agree)\n"
           "  --t-rel TOL       largest relative t difference for the same triangle,\n"
           "                    0..2 (default 1e-5)\n"
           "  --help            this text\n"
           "\n"
           "A ray agrees when both miss, or both hit the same triangle within --t-rel.\n"
           "Exit status 0: agreement within tolerance; 1: too many disagreements or bad\n"
           "input; 2: the files hold different numbers of records.\n");
}

/* |a - b| relative to the larger magnitude; NaN compares as infinitely far. */
static double relative_difference(float a, float b)
{
    double da = a, db = b, scale = fmax(fabs(da), fabs(db));
    if (da == db) return 0.0;
    if (isnan(da) || isnan(db) || isinf(scale)) return INFINITY;
    return fabs(da - db) / scale;
}

static void compare(const brt_hit *a, const brt_hit *b, size_t count, double t_rel,
                    agreement *g)
{
    size_t i;
    memset(g, 0, sizeof *g);
    g->rays = count;
    for (i = 0; i < count; i++) {
        int hit_a = a[i].prim != BRT_NO_PRIM, hit_b = b[i].prim != BRT_NO_PRIM;
        if (!hit_a && !hit_b) g->both_miss++;
        else if (hit_a && !hit_b) g->a_only++;
        else if (hit_b && !hit_a) g->b_only++;
        else if (a[i].prim != b[i].prim) g->different_prim++;
        else {
            double dt = relative_difference(a[i].t, b[i].t);
            g->same_prim++;
            g->t_over += !(dt <= t_rel);
            g->t_max = fmax(g->t_max, dt);
            g->t_sum += dt;
            g->uv_max = fmax(g->uv_max, fmax(fabs((double)a[i].u - b[i].u),
                                             fabs((double)a[i].v - b[i].v)));
        }
    }
}

static void print_count(const char *label, uint64_t n, uint64_t total)
{
    printf("%-34s %12llu  %8.4f %%\n", label, (unsigned long long)n,
           total ? 100.0 * (double)n / (double)total : 0.0);
}

static void print_table(const char *path_a, const char *path_b, const agreement *g,
                        double t_rel, uint64_t disagree)
{
    char label[64];
    printf("A: %s\nB: %s\n", path_a, path_b);
    printf("%-34s %12llu\n", "rays", (unsigned long long)g->rays);
    print_count("both miss", g->both_miss, g->rays);
    print_count("same prim", g->same_prim, g->rays);
    print_count("different prim (both hit)", g->different_prim, g->rays);
    print_count("hit in A only", g->a_only, g->rays);
    print_count("hit in B only", g->b_only, g->rays);
    printf("%-34s %12.3e\n", "same prim: max relative t diff", g->t_max);
    printf("%-34s %12.3e\n", "same prim: mean relative t diff",
           g->same_prim ? g->t_sum / (double)g->same_prim : 0.0);
    snprintf(label, sizeof label, "same prim: relative t diff > %g", t_rel);
    print_count(label, g->t_over, g->rays);
    printf("%-34s %12.3e\n", "same prim: max u,v diff", g->uv_max);
    print_count("disagreeing rays", disagree, g->rays);
}

int main(int argc, char **argv)
{
    const char *path_a = NULL, *path_b = NULL;
    double max_disagree = 0.0, t_rel = 1e-5, fraction;
    brt_hit *a, *b;
    size_t count_a, count_b;
    brt_error err;
    agreement g;
    uint64_t disagree;
    int i;

    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    for (i = 1; i < argc; i++) {
        const char *arg = argv[i];
        if (strcmp(arg, "--max-disagree") == 0)
            max_disagree = ex_parse_double(prog, arg, ex_option_value(prog, argc, argv, &i),
                                           0.0, 1.0);
        else if (strcmp(arg, "--t-rel") == 0)   /* 2 bounds every relative difference */
            t_rel = ex_parse_double(prog, arg, ex_option_value(prog, argc, argv, &i),
                                    0.0, 2.0);
        else if (arg[0] == '-' && arg[1] != 0)
            ex_die(prog, "unknown option '%s' (see --help)", arg);
        else if (!path_a) path_a = arg;
        else if (!path_b) path_b = arg;
        else ex_die(prog, "unexpected argument '%s' (see --help)", arg);
    }
    if (!path_b) ex_die(prog, "expected two hit files A.hits B.hits (see --help)");

    ex_check(prog, brt_hits_read(path_a, &a, &count_a, &err), &err);
    ex_check(prog, brt_hits_read(path_b, &b, &count_b, &err), &err);
    if (count_a != count_b) {
        fprintf(stderr, "%s: %s has %lu records but %s has %lu: not the same rays\n",
                prog, path_a, (unsigned long)count_a, path_b, (unsigned long)count_b);
        free(a);
        free(b);
        return 2;
    }

    compare(a, b, count_a, t_rel, &g);
    disagree = g.rays - g.both_miss - (g.same_prim - g.t_over);
    fraction = g.rays ? (double)disagree / (double)g.rays : 0.0;
    print_table(path_a, path_b, &g, t_rel, disagree);
    printf("%s: %llu of %llu rays disagree (%.4f %%, tolerated %.4f %%)\n",
           fraction <= max_disagree ? "AGREE" : "DISAGREE", (unsigned long long)disagree,
           (unsigned long long)g.rays, 100.0 * fraction, 100.0 * max_disagree);
    free(a);
    free(b);
    return fraction <= max_disagree ? 0 : 1;
}
