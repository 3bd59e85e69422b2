/*
** examples/tools/hitdiff.c -- compare two hit files ray by ray, e.g. batchrt's
** against an Embree build's, and print an agreement table.
**
**   build/hitdiff A.hits B.hits [--max-disagree FRACTION] [--t-rel TOL]
**   build/hitdiff A.hits B.hits --mesh MESH --rays RAYS [--explain FILE.csv]
**   build/hitdiff A.occ B.occ --occlusion [--max-disagree FRACTION]
**   build/hitdiff A.occ B.occ --occlusion --mesh MESH --rays RAYS [--explain FILE.csv]
**
** Tolerance mode (no --mesh): a ray agrees when both files miss it, or both
** hit the same triangle at distances whose relative difference
** |tA - tB| / max(|tA|, |tB|) is at most --t-rel.  Barycentrics are
** reported but never judged: two correct watertight tests may round them
** differently.  Exit status: 0 when the fraction of rays that disagree is
** at most --max-disagree, 1 when it is larger (or on bad input), 2 when the
** files hold different numbers of records (they cannot describe the same
** rays).
**
** Referee mode (--mesh and --rays): every ray whose records differ at all
** is refereed with exact arithmetic against the mesh and the ray
** (examples/lib/referee.c) and counted in one class; exit 0 when every
** disagreement is explained, 1 when one is not (or on bad input), 2 when
** the three files hold different numbers of records.  --explain writes one
** CSV line per disagreeing ray (under a temporary name, then renamed).
**
** Occlusion mode (--occlusion): A and B are occlusion files (one byte per
** ray, 0 or 1; README.md), compared byte by byte: both clear, both
** occluded, occluded in one only.  Chosen by the option, never guessed
** from the size (a file of 16 n bytes may be either).  --max-disagree
** applies.  With --mesh and --rays every ray whose bytes differ is
** refereed (ex_referee_occlusion: the candidates by brute force over the
** mesh, so each disagreeing ray costs one box test per triangle).
*/
#include "common.h"
#include "input.h"
#include "referee.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

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
           "       build/hitdiff A.hits B.hits --mesh MESH --rays RAYS [--explain FILE.csv]\n"
           "       build/hitdiff A.occ B.occ --occlusion [--mesh MESH --rays RAYS]\n"
           "Compares two hit files (16-byte records) ray by ray and prints a table.\n"
           "\n"
           "Tolerance mode (without --mesh):\n"
           "  --max-disagree F  largest tolerated fraction of disagreeing rays, 0..1\n"
           "                    (default 0: every ray must agree)\n"
           "  --t-rel TOL       largest relative t difference for the same triangle,\n"
           "                    0..2 (default 1e-5)\n"
           "A ray agrees when both miss, or both hit the same triangle within --t-rel.\n"
           "Exit status 0: agreement within tolerance; 1: too many disagreements or bad\n"
           "input; 2: the files hold different numbers of records.\n"
           "\n"
           "Referee mode:\n"
           "  --mesh MESH       the mesh both files traced (OBJ or PLY)\n"
           "  --rays RAYS       the ray file both traced (32-byte records)\n"
           "  --explain FILE    one CSV line per disagreeing ray: ray index, class,\n"
           "                    both records (t, prim, u, v) and the exact verdict\n"
           "A ray disagrees when its records differ at all (prim, hit/miss, t, u or v;\n"
           "two misses agree).  Each disagreement is refereed with exact arithmetic\n"
           "(orientation predicates on floating-point expansions, Shewchuk 1997): on\n"
           "which side of each edge the ray passes, and where along it each named\n"
           "triangle is met.  Classes:\n"
           "  tie          both right: two triangles hit at exactly the same t\n"
           "  near tie     two triangles hit, exact t closer than the t bound\n"
           "  t bound      the same triangle, each t within the bound for this ray:\n"
           "               16 eps (L1 L2 (R + |t| |d|) / |n.d| + |t|), L1, L2 the\n"
           "               longest edges, R the farthest vertex from the origin,\n"
           "               n the triangle's normal, eps = FLT_EPSILON = 2^-23\n"
           "  A/B leaks    the ray passes through the closed triangle the other side\n"
           "               hits, within rounding of an edge or vertex (an edge function\n"
           "               within 16 eps (|a-o| |(b-o) x d| + |b-o| |(a-o) x d|) of 0),\n"
           "               and this side reports a miss or a farther hit\n"
           "  A/B outside  this side hits a triangle the ray passes just outside of,\n"
           "               within rounding of an edge or vertex\n"
           "  boundary     the hit's exact t is within rounding of tnear or tfar\n"
           "  unexplained  anything else: a real disagreement\n"
           "Exit status 0: every disagreement explained; 1: some unexplained, or bad\n"
           "input (a missing file, a prim beyond the mesh); 2: the files hold\n"
           "different numbers of records.\n"
           "\n"
           "Occlusion mode:\n"
           "  --occlusion       A and B are occlusion files (one byte per ray, 0 clear,\n"
           "                    1 occluded); counts both clear, both occluded and each\n"
           "                    one-sided answer; --max-disagree as above\n"
"  --occlusion --mesh MESH --rays RAYS [--explain FILE]\n"
           "                    referees each ray whose bytes differ: the candidates are\n"
           "                    the triangles whose padded boxes [tnear, tfar] enters\n"
           "                    (brute force, per disagreeing ray), each judged exactly;\n"
           "                    the side saying 0 leaks when the only exact hits are at\n"
           "                    an edge or vertex, the side saying 1 hits just outside\n"
           "                    when no hit is exact but one is within an edge band\n"
           "\n"
           "  --help            this text\n");
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

/* ===================================================================== */
/* Occlusion mode                                                        */
/* ===================================================================== */

/* An occlusion file whole (malloc'd): every byte must be 0 or 1. */
static uint8_t *read_occlusion(const char *path, size_t *count)
{
    FILE *f = fopen(path, "rb");
    uint8_t *bytes = NULL;
    size_t cap = 0, n = 0, i;
    if (!f) ex_die(prog, "%s: cannot open: %s", path, strerror(errno));
    for (;;) {
        if (n == cap && !(bytes = brt_grow(bytes, &cap, n + 65536, 1)))
            ex_die(prog, "%s: out of memory", path);
        i = fread(bytes + n, 1, cap - n, f);
        n += i;
        if (i == 0) break;
    }
    if (ferror(f)) ex_die(prog, "%s: cannot read: %s", path, strerror(errno));
    fclose(f);
    for (i = 0; i < n; i++)
        if (bytes[i] > 1)
            ex_die(prog, "%s: byte %lu is %u, not 0 or 1: not an occlusion file", path,
                   (unsigned long)i, (unsigned)bytes[i]);
    *count = n;
    return bytes;
}

/* Nonzero when two files hold as many records; otherwise says so. */
static int same_count(const char *path_a, size_t count_a, const char *path_b, size_t count_b)
{
    if (count_a == count_b) return 1;
    fprintf(stderr, "%s: %s has %lu records but %s has %lu: not the same rays\n",
            prog, path_a, (unsigned long)count_a, path_b, (unsigned long)count_b);
    return 0;
}

/* Compares two occlusion files; returns the exit status. */
static int occlusion_main(const char *path_a, const char *path_b, double max_disagree)
{
    size_t count_a, count_b, i;
    uint8_t *a = read_occlusion(path_a, &count_a), *b = read_occlusion(path_b, &count_b);
    uint64_t kinds[2][2] = {{0, 0}, {0, 0}}, disagree;
    double fraction;
    if (!same_count(path_a, count_a, path_b, count_b)) {
        free(a);
        free(b);
        return 2;
    }
    for (i = 0; i < count_a; i++) kinds[a[i]][b[i]]++;
    disagree = kinds[1][0] + kinds[0][1];
    fraction = count_a ? (double)disagree / (double)count_a : 0.0;
    printf("A: %s\nB: %s\n", path_a, path_b);
    printf("%-34s %12llu\n", "rays", (unsigned long long)count_a);
    print_count("both clear", kinds[0][0], count_a);
    print_count("both occluded", kinds[1][1], count_a);
    print_count("occluded in A only", kinds[1][0], count_a);
    print_count("occluded in B only", kinds[0][1], count_a);
    printf("%s: %llu of %llu rays disagree (%.4f %%, tolerated %.4f %%)\n",
           fraction <= max_disagree ? "AGREE" : "DISAGREE", (unsigned long long)disagree,
           (unsigned long long)count_a, 100.0 * fraction, 100.0 * max_disagree);
    free(a);
    free(b);
    return fraction <= max_disagree ? 0 : 1;
}

/* ===================================================================== */
/* Referee mode                                                          */
/* ===================================================================== */

typedef struct referee_run {
    const char *path[2];          /* A.hits, B.hits (or A.occ, B.occ) */
    const brt_hit *hits[2];
    const uint8_t *occluded[2];   /* occlusion files instead of hits[] */
    const char *mesh_path, *rays_path, *explain_path;
    const brt_mesh *mesh;
    const ex_instanced_mesh *instanced;   /* a .pbrt scene, else NULL */
    const brt_ray *rays;
    size_t count;
    uint64_t disagree, classes[EX_CLASSES];
    double t_ratio, edge_ratio;   /* the largest of ex_verdict's, explained rays */
} referee_run;

/* Bad input before any refereeing: a prim the mesh does not have. */
static void check_prims(const referee_run *run)
{
    size_t i;
    int f;
    if (run->occluded[0] || run->instanced) return;   /* an occlusion byte names no prim;
                                                       ** the instanced referee checks its own */
    for (f = 0; f < 2; f++)
        for (i = 0; i < run->count; i++) {
            const uint32_t prim = run->hits[f][i].prim;
            if (prim != BRT_NO_PRIM && prim >= run->mesh->triangle_count)
                ex_die(prog, "%s: record %lu: prim %lu beyond the %lu triangles of %s",
                       run->path[f], (unsigned long)i, (unsigned long)prim,
                       (unsigned long)run->mesh->triangle_count, run->mesh_path);
        }
}

static void print_record(FILE *f, const brt_hit *h)
{
    fprintf(f, ",%.9g,%ld,%.9g,%.9g", h->t, h->prim == BRT_NO_PRIM ? -1L : (long)h->prim,
            h->u, h->v);
}

/* Referees ray i into *verdict when its two records disagree; returns
** whether they do. */
static int referee_ray(const referee_run *run, size_t i, ex_verdict *verdict)
{
    if (run->occluded[0]) {
        const int a = run->occluded[0][i], b = run->occluded[1][i];
        if (a == b) return 0;
        ex_referee_occlusion(run->mesh, &run->rays[i], a, b, verdict);
    } else {
        const brt_hit *a = &run->hits[0][i], *b = &run->hits[1][i];
        if (!ex_hits_disagree(a, b)) return 0;
        if (run->instanced) ex_referee_instanced(run->instanced, &run->rays[i], a, b, verdict);
        else ex_referee(run->mesh, &run->rays[i], a, b, verdict);
    }
    return 1;
}

/* Referees every disagreeing ray; with --explain, one CSV line each, into
** a temporary file renamed at the end (never a half-written FILE.csv). */
static void referee_all(referee_run *run)
{
    brt_atomic_file file;
    brt_error err;
    ex_verdict verdict;
    FILE *csv = NULL;
    size_t i;
    if (run->explain_path) {
        ex_check(prog, brt_atomic_open(&file, run->explain_path, &err), &err);
        if (!(csv = fdopen(file.fd, "w"))) {
            brt_result r = brt_fail(&err, BRT_EIO, "%s: cannot create: %s", run->explain_path,
                                    strerror(errno));
            ex_check(prog, brt_atomic_close(&file, r, &err), &err);
        }
        fprintf(csv, run->occluded[0] ? "ray,class,a,b,verdict\n"
                     : "ray,class,a_t,a_prim,a_u,a_v,b_t,b_prim,b_u,b_v,verdict\n");
    }
    for (i = 0; i < run->count && !ex_interrupted(); i++) {
        if (!referee_ray(run, i, &verdict)) continue;
        run->disagree++;
        run->classes[verdict.cls]++;
        if (verdict.cls != EX_UNEXPLAINED) {
            run->t_ratio = fmax(run->t_ratio, verdict.t_ratio);
            run->edge_ratio = fmax(run->edge_ratio, verdict.edge_ratio);
        }
        if (csv) {
            fprintf(csv, "%lu,%s", (unsigned long)i, ex_class_id[verdict.cls]);
            if (run->occluded[0])
                fprintf(csv, ",%d,%d", run->occluded[0][i], run->occluded[1][i]);
            else {
                print_record(csv, &run->hits[0][i]);
                print_record(csv, &run->hits[1][i]);
            }
            fprintf(csv, ",\"%s\"\n", verdict.text);
        }
    }
    if (csv) {
        brt_result r = BRT_OK;
        int failed = ferror(csv);
        failed |= fclose(csv) != 0;   /* closes in any case */
        file.fd = -1;
        if (failed)
            r = brt_fail(&err, BRT_EIO, "%s: cannot write: %s", run->explain_path,
                         errno ? strerror(errno) : "write error");
        else if (ex_interrupted())
            r = brt_fail(&err, BRT_EINTR, "%s: interrupted", run->explain_path);
        ex_check(prog, brt_atomic_close(&file, r, &err), &err);   /* removes it unless r is BRT_OK */
    }
    if (ex_interrupted()) ex_die_interrupted(prog);
}

static void print_referee_table(const referee_run *run)
{
    const uint64_t rays = run->count;
    int c;
    printf("A: %s\nB: %s\n", run->path[0], run->path[1]);
    printf("refereed on %s (%lu triangles) and %s\n", run->mesh_path,
           (unsigned long)run->mesh->triangle_count, run->rays_path);
    printf("%-38s %12llu\n", "rays", (unsigned long long)rays);
    printf("%-38s %12llu  %8.4f %%\n", "agree (identical records, or both miss)",
           (unsigned long long)(rays - run->disagree),
           rays ? 100.0 * (double)(rays - run->disagree) / (double)rays : 0.0);
    printf("%-38s %12llu  %8.4f %%\n", "disagree", (unsigned long long)run->disagree,
           rays ? 100.0 * (double)run->disagree / (double)rays : 0.0);
    for (c = 0; c < EX_CLASSES; c++)
        printf("  %-36s %12llu\n", ex_class_label[c], (unsigned long long)run->classes[c]);
    printf("%-38s %12.3g\n", "largest |t - exact t| / t bound", run->t_ratio);
    printf("%-38s %12.3g\n", "largest |E| / edge band, edge classes", run->edge_ratio);
    if (run->classes[EX_UNEXPLAINED] == 0)
        printf("EXPLAINED: all %llu disagreeing rays of %llu explained\n",
               (unsigned long long)run->disagree, (unsigned long long)rays);
    else
        printf("UNEXPLAINED: %llu of %llu disagreeing rays of %llu unexplained\n",
               (unsigned long long)run->classes[EX_UNEXPLAINED],
               (unsigned long long)run->disagree, (unsigned long long)rays);
}

/* Loads the mesh and the rays, checks the three files describe the same
** rays, referees, prints; returns the exit status. */
static int referee_main(referee_run *run)
{
    brt_mesh mesh;
    ex_instanced_mesh instanced;
    ex_input input;
    brt_ray *rays;
    size_t ray_count;
    brt_error err;
    memset(&mesh, 0, sizeof mesh);
    memset(&instanced, 0, sizeof instanced);
    ex_catch_interrupts();   /* the referee polls it; a failed load reports it (ex_check) */
    ex_input_open(prog, run->mesh_path, &input);
    if (input.pbrt) {
        if (run->occluded[0])
            ex_die(prog, "%s: --occlusion is refereed on meshes only, not on pbrt scenes",
                   run->mesh_path);
        ex_check(prog, ex_instanced_mesh_load(&input.source, &instanced, &err), &err);
        run->instanced = &instanced;
        mesh = instanced.world;
    } else {
        ex_check(prog, brt_mesh_load(run->mesh_path, &mesh, &err), &err);
    }
    ex_check(prog, brt_rays_read(run->rays_path, &rays, &ray_count, &err), &err);
    if (ray_count != run->count) {
        fprintf(stderr, "%s: %s has %lu rays but %s has %lu records: not the same rays\n",
                prog, run->rays_path, (unsigned long)ray_count, run->path[0],
                (unsigned long)run->count);
        free(rays);
        if (run->instanced) ex_instanced_mesh_free(&instanced);
        else brt_mesh_free(&mesh);
        ex_input_close(&input);
        return 2;
    }
    run->mesh = &mesh;
    run->rays = rays;
    check_prims(run);
    referee_all(run);
    print_referee_table(run);
    free(rays);
    if (run->instanced) ex_instanced_mesh_free(&instanced);
    else brt_mesh_free(&mesh);
    ex_input_close(&input);
    return run->classes[EX_UNEXPLAINED] ? 1 : 0;
}

/* Referees two occlusion files; returns the exit status. */
static int occlusion_referee_main(referee_run *run, const char *path_a, const char *path_b)
{
    size_t count_a, count_b;
    uint8_t *a = read_occlusion(path_a, &count_a), *b = read_occlusion(path_b, &count_b);
    int status = 2;
    if (same_count(path_a, count_a, path_b, count_b)) {
        run->path[0] = path_a;
        run->path[1] = path_b;
        run->occluded[0] = a;
        run->occluded[1] = b;
        run->count = count_a;
        status = referee_main(run);
    }
    free(a);
    free(b);
    return status;
}

/* ===================================================================== */
/* Command line                                                          */
/* ===================================================================== */

int main(int argc, char **argv)
{
    const char *path_a = NULL, *path_b = NULL;
    double max_disagree = 0.0, t_rel = 1e-5, fraction;
    referee_run run;
    int tolerance_options = 0, occlusion = 0;
    brt_hit *a, *b;
    size_t count_a, count_b;
    brt_error err;
    agreement g;
    uint64_t disagree;
    int i;

    memset(&run, 0, sizeof run);
    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    for (i = 1; i < argc; i++) {
        const char *arg = argv[i];
        if (strcmp(arg, "--max-disagree") == 0) {
            max_disagree = ex_parse_double(prog, arg, ex_option_value(prog, argc, argv, &i),
                                           0.0, 1.0);
            tolerance_options = 1;
        } else if (strcmp(arg, "--t-rel") == 0) {   /* 2 bounds every relative difference */
            t_rel = ex_parse_double(prog, arg, ex_option_value(prog, argc, argv, &i),
                                    0.0, 2.0);
            tolerance_options = 1;
        } else if (strcmp(arg, "--occlusion") == 0)
            occlusion = 1;
        else if (strcmp(arg, "--mesh") == 0)
            run.mesh_path = ex_option_value(prog, argc, argv, &i);
        else if (strcmp(arg, "--rays") == 0)
            run.rays_path = ex_option_value(prog, argc, argv, &i);
        else if (strcmp(arg, "--explain") == 0)
            run.explain_path = ex_option_value(prog, argc, argv, &i);
        else if (arg[0] == '-' && arg[1] != 0)
            ex_unknown_option(prog, arg);
        else if (!path_a) path_a = arg;
        else if (!path_b) path_b = arg;
        else ex_die(prog, "unexpected argument '%s' (see --help)", arg);
    }
    if (!path_b) ex_die(prog, "expected two hit files A.hits B.hits (see --help)");
    if ((run.mesh_path || run.explain_path) && !run.rays_path)
        ex_die(prog, "--mesh and --explain need --rays RAYS (see --help)");
    if ((run.rays_path || run.explain_path) && !run.mesh_path)
        ex_die(prog, "--rays and --explain need --mesh MESH (see --help)");
    if (run.mesh_path && tolerance_options)
        ex_die(prog, "--max-disagree and --t-rel are for tolerance mode, not with --mesh "
               "(see --help)");
    if (occlusion && run.mesh_path) return occlusion_referee_main(&run, path_a, path_b);
    if (occlusion) return occlusion_main(path_a, path_b, max_disagree);

    ex_check(prog, brt_hits_read(path_a, &a, &count_a, NULL, &err), &err);
    ex_check(prog, brt_hits_read(path_b, &b, &count_b, NULL, &err), &err);
    if (!same_count(path_a, count_a, path_b, count_b)) {
        free(a);
        free(b);
        return 2;
    }

    if (run.mesh_path) {
        int status;
        run.path[0] = path_a;
        run.path[1] = path_b;
        run.hits[0] = a;
        run.hits[1] = b;
        run.count = count_a;
        status = referee_main(&run);
        free(a);
        free(b);
        return status;
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
