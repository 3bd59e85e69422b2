/*
** tests/test_embree.c -- batchrt against Embree 3, ray by ray (issue 6).
**
** Runs only when $BRT_BUILD/embree_trace exists ("make embree"); otherwise
** one visible skip.  For each mesh (the built-in scenes from build/mkscene
** and a shared scan) and each kind of rays (camera, random and bounce from
** build/raygen; "edge" rays aimed at triangle edges and vertices, made
** here), the hit files of build/trace --direct, build/trace --batched and
** build/embree_trace (Embree's default mode and --robust) are compared:
**
**   - direct and batched must be byte-identical (batchrt's own contract);
**   - for raygen's rays, at least 99.99 % must have the same hit/miss and
**     prim in batchrt and Embree;
**   - every other ray must fall into a class where both tracers are right
**     (classify(), whose oracles are brt_intersect_triangle and geometry in
**     double precision), or the test fails and prints the ray;
**   - build/hitdiff, the user's tool, must say "agree" exactly when the
**     count here says so.
** The classifier is itself tested on hand-made answers, without Embree.
*/
#include "test.h"
#include "batchrt.h"

#include <float.h>
#include <math.h>
#include <stdarg.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

/* Rays per mesh and kind; BRT_EMBREE_RAYS=N overrides it for a longer run
** (with BRT_EMBREE_TABLE=1 the test prints its table even when it passes). */
#define RAYS_PER_KIND 40000
#define MIN_IDENTICAL 0.9999  /* fraction of rays with the same hit/miss and prim */
#define T_REL 1e-5            /* same prim: largest relative t difference */
#define HITDIFF_MAX_DISAGREE 1e-4
/* The rounding bound of an edge function, in float ulps (see near_edge). */
#define EDGE_ULPS 16.0

/* ===================================================================== */
/* Programs and files                                                    */
/* ===================================================================== */

static const char *build_dir(void)
{
    const char *build = getenv("BRT_BUILD");
    return build ? build : "build";
}

static long rays_per_kind(void)
{
    const char *text = getenv("BRT_EMBREE_RAYS");
    long n = text ? strtol(text, NULL, 10) : 0;
    return n > 0 ? n : RAYS_PER_KIND;
}

/* NAME inside the scratch directory, in a buffer of the caller. */
static const char *scratch(char path[512], const char *name)
{
    snprintf(path, 512, "%s/%s", test_tmpdir(), name);
    return path;
}

/* Runs "$BRT_BUILD/PROGRAM ARGS" (printf-formatted) with its output in
** embree.log in the scratch directory; returns the exit status. */
static int run(const char *fmt, ...)
{
    char args[2048], cmd[4096], log[512];
    va_list ap;
    int status;
    va_start(ap, fmt);
    vsnprintf(args, sizeof args, fmt, ap);
    va_end(ap);
    snprintf(cmd, sizeof cmd, "%s/%s > %s 2>&1", build_dir(), args, scratch(log, "embree.log"));
    status = system(cmd);
    return status == -1 ? -1 : (status >> 8) & 0xFF;
}

static brt_hit *read_hits(const char *path, size_t count)
{
    brt_hit *hits;
    size_t n;
    brt_error err;
    if (brt_hits_read(path, &hits, &n, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s", err.message);
        return NULL;
    }
    if (n != count) {
        test_fail_at(__FILE__, __LINE__, "%s: %lu hits for %lu rays", path,
                     (unsigned long)n, (unsigned long)count);
        free(hits);
        return NULL;
    }
    return hits;
}

/* ===================================================================== */
/* Classifying a disagreement                                            */
/* ===================================================================== */

enum verdict {
    SAME,        /* both miss, or the same prim within T_REL */
    TIE,         /* different prims, both hit at the same t (a shared edge/vertex) */
    LEAK,        /* batchrt's hit is at an edge that Embree passed through */
    EDGE,        /* Embree's hit is at an edge that batchrt's test passed by */
    ILL_CONDITIONED, /* same prim, t apart by more than T_REL: both within
                        the rounding bound of an ill-conditioned t */
    TNEAR,       /* batchrt's hit at t == tnear, which Embree excludes */
    UNEXPLAINED,
    VERDICTS
};
static const char *const verdict_name[VERDICTS] = {
    "same", "tie", "Embree leak", "Embree edge hit", "ill-conditioned t", "tnear", "unexplained"};

static double relative_difference(double a, double b)
{
    double scale = fmax(fabs(a), fabs(b));
    return a == b ? 0.0 : fabs(a - b) / scale;
}

static void triangle(const brt_mesh *mesh, uint32_t prim, const float *v[3])
{
    int k;
    for (k = 0; k < 3; k++) v[k] = mesh->positions + 3 * (size_t)mesh->indices[3 * prim + k];
}

/* The oracle's t for ray and prim, or NaN when the watertight test misses. */
static float oracle_t(const brt_mesh *mesh, const brt_ray *ray, uint32_t prim)
{
    const float *v[3];
    float t, u, w;
    triangle(mesh, prim, v);
    return brt_intersect_triangle(ray, v[0], v[1], v[2], &t, &u, &w) ? t : NAN;
}

/* Nonzero when the ray passes prim at one of its edges (or vertices),
** closer than a float ray/triangle test can resolve.  Every such test
** decides inside/outside by the signs of three edge functions, in exact
** terms E_ab = ((a - org) x (b - org)) . dir for each edge ab, computed in
** float from vertices relative to the origin (Woop et al. after a shear,
** Moeller-Trumbore and Pluecker alike), so their rounding is a few ulps of
** |a - org| |b - org| |dir|.  "At an edge": every E (oriented to be
** positive inside) is above minus that bound, and one is below it.  For
** rays that graze the plane from far away every E is tiny, and the answer
** is rounding, as it should be. */
static int near_edge(const brt_mesh *mesh, const brt_ray *ray, uint32_t prim)
{
    const float *v[3];
    double r[3][3], len[3], edge[3], bound[3], sum = 0, d = 0;
    int i, k, inside = 1, at_edge = 0;
    triangle(mesh, prim, v);
    for (i = 0; i < 3; i++) {
        len[i] = 0;
        for (k = 0; k < 3; k++) {
            r[i][k] = (double)v[i][k] - ray->org[k];
            len[i] += r[i][k] * r[i][k];
        }
        len[i] = sqrt(len[i]);
        d += (double)ray->dir[i] * ray->dir[i];
    }
    for (i = 0; i < 3; i++) {
        const double *a = r[i], *b = r[(i + 1) % 3];
        edge[i] = (a[1] * b[2] - a[2] * b[1]) * ray->dir[0]
                + (a[2] * b[0] - a[0] * b[2]) * ray->dir[1]
                + (a[0] * b[1] - a[1] * b[0]) * ray->dir[2];
        bound[i] = EDGE_ULPS * FLT_EPSILON * len[i] * len[(i + 1) % 3] * sqrt(d);
        sum += edge[i];
    }
    for (i = 0; i < 3; i++) {
        const double e = sum < 0 ? -edge[i] : edge[i];
        inside &= e >= -bound[i];
        at_edge |= e <= bound[i];
    }
    return inside && at_edge;
}

/* Ill-conditioned t: a float ray/triangle test computes t from products
** of size |n||v0 - org| and |n||dir| (n the triangle's normal), so its
** error can reach about eps * |n| (|v0 - org| + t |dir|) / |n.dir|: large
** when the ray grazes the plane, or starts far from v0 compared with t (a
** huge triangle near the origin).  Returns that bound (times 16, for the
** few roundings of each product) and sets *t to the plane's t in double. */
static double plane_t_error(const brt_mesh *mesh, const brt_ray *ray, uint32_t prim,
                            double *t)
{
    const float *v[3];
    double e1[3], e2[3], n[3], c[3], nn = 0, dd = 0, cc = 0, nc = 0, nd = 0;
    int k;
    triangle(mesh, prim, v);
    for (k = 0; k < 3; k++) {
        e1[k] = (double)v[1][k] - v[0][k];
        e2[k] = (double)v[2][k] - v[0][k];
        c[k] = (double)v[0][k] - ray->org[k];
    }
    for (k = 0; k < 3; k++) {
        n[k] = e1[(k + 1) % 3] * e2[(k + 2) % 3] - e1[(k + 2) % 3] * e2[(k + 1) % 3];
        nn += n[k] * n[k];
        dd += (double)ray->dir[k] * ray->dir[k];
        cc += c[k] * c[k];
        nc += n[k] * c[k];
        nd += n[k] * ray->dir[k];
    }
    *t = nc / nd;
    return 16.0 * FLT_EPSILON * sqrt(nn) * (sqrt(cc) + fabs(*t) * sqrt(dd)) / fabs(nd);
}

/* Both answers on one prim, t apart by more than T_REL: right when both
** are within the rounding bound of the plane's t. */
static int both_within_conditioning(const brt_mesh *mesh, const brt_ray *ray, uint32_t prim,
                                    float t_ours, float t_theirs)
{
    double t, bound = plane_t_error(mesh, ray, prim, &t);
    return fabs(t_ours - t) <= bound && fabs(t_theirs - t) <= bound;
}

/* Hits on two prims at "the same t": within T_REL, or within the sum of
** the two planes' rounding bounds (then the order can flip either way). */
static int same_t(const brt_mesh *mesh, const brt_ray *ray, const brt_hit *a,
                  const brt_hit *b)
{
    double ta, tb;
    double bound = plane_t_error(mesh, ray, a->prim, &ta) + plane_t_error(mesh, ray, b->prim, &tb);
    return relative_difference(a->t, b->t) <= T_REL || fabs((double)a->t - b->t) <= bound;
}

/* ours: batchrt's hit; theirs: Embree's.  Both answers are right in every
** class but UNEXPLAINED. */
static enum verdict classify(const brt_mesh *mesh, const brt_ray *ray, const brt_hit *ours,
                             const brt_hit *theirs)
{
    const int hit_ours = ours->prim != BRT_NO_PRIM, hit_theirs = theirs->prim != BRT_NO_PRIM;
    if (hit_theirs && theirs->prim >= mesh->triangle_count) return UNEXPLAINED;
    if (!hit_ours && !hit_theirs) return SAME;
    if (hit_ours && hit_theirs && ours->prim == theirs->prim) {
        if (relative_difference(ours->t, theirs->t) <= T_REL) return SAME;
        return both_within_conditioning(mesh, ray, ours->prim, ours->t, theirs->t)
                   ? ILL_CONDITIONED : UNEXPLAINED;
    }
    if (hit_ours && ours->t == ray->tnear && (!hit_theirs || theirs->t > ours->t)) return TNEAR;
    /* Two prims at the same t: a tie when our own test hits Embree's prim
    ** too, or the ray passes at its edge, which our test resolved the other
    ** way (the prims then share that edge or vertex). */
    if (hit_ours && hit_theirs && same_t(mesh, ray, ours, theirs)
        && (!isnan(oracle_t(mesh, ray, theirs->prim)) || near_edge(mesh, ray, theirs->prim)))
        return TIE;
    /* One side sees a hit that the other goes past: right only at an edge,
    ** where rounding decides, and for Embree's hit only when our own test
    ** misses its prim (else batchrt's traversal lost a hit). */
    if (hit_ours && (!hit_theirs || theirs->t > ours->t))
        return near_edge(mesh, ray, ours->prim) ? LEAK : UNEXPLAINED;
    return near_edge(mesh, ray, theirs->prim) && isnan(oracle_t(mesh, ray, theirs->prim))
               ? EDGE : UNEXPLAINED;
}

/* ===================================================================== */
/* One mesh: rays, four hit files, comparisons                          */
/* ===================================================================== */

typedef struct tally {
    uint64_t rays, identical;        /* same hit/miss and same prim */
    uint64_t verdicts[VERDICTS];
} tally;

static void print_ray(const char *what, const brt_mesh *mesh, const brt_ray *r,
                      const brt_hit *ours, const brt_hit *theirs)
{
    const int hit_theirs = theirs->prim != BRT_NO_PRIM;
    test_fail_at(__FILE__, __LINE__,
                 "%s: ray org (%.9g %.9g %.9g) dir (%.9g %.9g %.9g) t [%.9g %.9g]: "
                 "batchrt t %.9g prim %lu u %.9g v %.9g, Embree t %.9g prim %lu u %.9g v %.9g; "
                 "brt_intersect_triangle on Embree's prim: t %.9g, at its edge: %s",
                 what, r->org[0], r->org[1], r->org[2], r->dir[0], r->dir[1], r->dir[2],
                 r->tnear, r->tfar, ours->t, (unsigned long)ours->prim, ours->u, ours->v,
                 theirs->t, (unsigned long)theirs->prim, theirs->u, theirs->v,
                 hit_theirs ? oracle_t(mesh, r, theirs->prim) : NAN,
                 hit_theirs && near_edge(mesh, r, theirs->prim) ? "yes" : "no");
}

/* Every ray of one Embree hit file against batchrt's; failures print rays.
** The rays of raygen must agree on hit/miss and prim for MIN_IDENTICAL of
** them; edge rays (write_edge_rays) aim at the disagreements, so for them
** only the classification counts. */
static void compare_with_embree(const char *label, const brt_mesh *mesh, const brt_ray *rays,
                                size_t count, const brt_hit *ours, const brt_hit *theirs,
                                int edge_rays, tally *tl)
{
    size_t i;
    int printed = 0;
    memset(tl, 0, sizeof *tl);
    tl->rays = count;
    for (i = 0; i < count; i++) {
        enum verdict v = classify(mesh, &rays[i], &ours[i], &theirs[i]);
        tl->identical += ours[i].prim == theirs[i].prim;
        tl->verdicts[v]++;
        if (v == UNEXPLAINED && printed++ < 5) print_ray(label, mesh, &rays[i], &ours[i], &theirs[i]);
    }
    EXPECT(edge_rays || (double)tl->identical >= MIN_IDENTICAL * (double)count,
           "%s: only %llu of %llu rays have the same hit/miss and prim (< %.2f %%)", label,
           (unsigned long long)tl->identical, (unsigned long long)count, 100 * MIN_IDENTICAL);
}

static void print_tally(const char *label, const tally *tl)
{
    int v;
    printf("  %-28s %7llu rays %8.4f %% identical", label, (unsigned long long)tl->rays,
           100.0 * (double)tl->identical / (double)tl->rays);
    for (v = TIE; v < VERDICTS; v++)
        if (tl->verdicts[v])
            printf(", %s %llu", verdict_name[v], (unsigned long long)tl->verdicts[v]);
    printf("\n");
}

static int same_bytes(const brt_hit *a, const brt_hit *b, size_t count)
{
    return memcmp(a, b, count * sizeof *a) == 0;
}

/* The user's workflow: build/hitdiff with the tolerances of this test must
** say "agree" exactly when the count here says so (a ray agrees when it is
** SAME), whatever the rays that hitdiff cannot classify. */
static void expect_hitdiff_verdict(const char *label, const char *ours, const char *theirs,
                                   const tally *tl)
{
    const double disagree = (double)(tl->rays - tl->verdicts[SAME]) / (double)tl->rays;
    const int expected = disagree <= HITDIFF_MAX_DISAGREE ? 0 : 1;
    int status = run("hitdiff '%s' '%s' --max-disagree %g --t-rel %g", ours, theirs,
                     HITDIFF_MAX_DISAGREE, T_REL);
    EXPECT(status == expected, "%s: hitdiff %s %s: exit status %d, expected %d "
           "(%.4f %% disagree)", label, ours, theirs, status, expected, 100.0 * disagree);
}

/* The hardest rays for a ray/triangle test that is not watertight: from
** random points of the mesh's box (grown by half its size) at random
** points of triangle edges (one ray in four at a vertex), rounded to
** float, so they cross the edge within a few ulps. */
static int write_edge_rays(const brt_mesh *mesh, const char *path)
{
    const long count = rays_per_kind();
    uint64_t rng = test_seed();
    float lo[3], hi[3];
    brt_ray *rays = malloc((size_t)count * sizeof *rays);
    brt_result r;
    long i;
    int k;
    if (!rays) return 0;
    brt_mesh_bounds(mesh, lo, hi);
    for (i = 0; i < count; i++) {
        const float *v[3];
        const uint32_t prim = (uint32_t)(brt_random_u64(&rng) % mesh->triangle_count);
        const int corner = (int)(brt_random_u64(&rng) % 3);
        const float s = brt_random_u64(&rng) % 4 == 0 ? 0.0f : brt_random_float(&rng);
        triangle(mesh, prim, v);
        for (k = 0; k < 3; k++) {
            const float target = v[corner][k] + s * (v[(corner + 1) % 3][k] - v[corner][k]);
            const float size = hi[k] - lo[k];
            rays[i].org[k] = lo[k] - 0.5f * size + 2.0f * size * brt_random_float(&rng);
            rays[i].dir[k] = target - rays[i].org[k];
        }
        rays[i].tnear = 0.0f;
        rays[i].tfar = INFINITY;
    }
    r = brt_rays_write(path, rays, (size_t)count, NULL);
    free(rays);
    return r == BRT_OK;
}

/* Runs a tracer as "PROGRAM MESH RAYS HITS OPTIONS" and reads its hits;
** NULL, with a failure that quotes the program's output, when it fails. */
static brt_hit *trace_with(const char *program, const char *options, const char *mesh,
                           const char *rays, const char *hits, size_t count)
{
    char log[512], text[300] = "";
    FILE *f;
    if (run("%s '%s' '%s' '%s' %s", program, mesh, rays, hits, options) == 0)
        return read_hits(hits, count);
    if ((f = fopen(scratch(log, "embree.log"), "r")) != NULL) {
        text[fread(text, 1, sizeof text - 1, f)] = 0;
        fclose(f);
    }
    test_fail_at(__FILE__, __LINE__, "%s %s failed: %s", program, options, text);
    return NULL;
}

/* One ray kind on one mesh: direct, batched, Embree and Embree robust. */
static void check_kind(const char *mesh_path, const brt_mesh *mesh, const char *kind,
                       const char *label)
{
    static const char *const modes[2] = {"", "--robust"};
    const int edge_rays = strcmp(kind, "edge") == 0;
    char rays_path[512], direct_path[512], batched_path[512], embree_path[512], scene[512];
    char batched_options[1024];
    brt_hit *direct, *batched, *embree[2] = {NULL, NULL};
    brt_ray *rays = NULL;
    size_t count;
    brt_error err;
    tally tl[2];
    int m;

    scratch(rays_path, "embree.rays");
    scratch(direct_path, "direct.hits");
    scratch(batched_path, "batched.hits");
    scratch(embree_path, "embree.hits");
    /* Small batching points, coarse proxies and a tiny cache: many loads. */
    snprintf(batched_options, sizeof batched_options,
             "--batched --batch-tris 4000 --res 32 --memory 256K --scene '%s'",
             scratch(scene, "embree.brs"));
    if (edge_rays)
        CHECK(write_edge_rays(mesh, rays_path), "%s: cannot write %s", label, rays_path);
    else
        CHECK(run("raygen '%s' '%s' --kind %s --count %ld --seed %llu", mesh_path, rays_path,
                  kind, rays_per_kind(), (unsigned long long)test_seed()) == 0,
              "%s: raygen failed", label);
    CHECK(brt_rays_read(rays_path, &rays, &count, &err) == BRT_OK, "%s", err.message);
    direct = trace_with("trace", "--direct", mesh_path, rays_path, direct_path, count);
    batched = trace_with("trace", batched_options, mesh_path, rays_path, batched_path, count);
    if (direct && batched)
        EXPECT(same_bytes(direct, batched, count),
               "%s: trace --batched differs from --direct", label);
    for (m = 0; m < 2; m++) {
        embree[m] = trace_with("embree_trace", modes[m], mesh_path, rays_path, embree_path,
                               count);
        if (direct && embree[m]) {
            compare_with_embree(label, mesh, rays, count, direct, embree[m], edge_rays,
                                &tl[m]);
            expect_hitdiff_verdict(label, direct_path, embree_path, &tl[m]);
        }
    }
    if (test_failed() || getenv("BRT_EMBREE_TABLE")) {
        printf("%s: direct == batched: %s\n", label,
               direct && batched && same_bytes(direct, batched, count) ? "yes" : "NO");
        for (m = 0; m < 2 && direct; m++)
            if (embree[m]) print_tally(m ? "vs Embree --robust" : "vs Embree", &tl[m]);
    }
    free(rays);
    free(direct);
    free(batched);
    free(embree[0]);
    free(embree[1]);
}

static void check_mesh(const char *mesh_path, const char *name)
{
    static const char *const kinds[] = {"camera", "random", "bounce", "edge"};
    char label[128];
    brt_mesh mesh;
    brt_error err;
    char scene[512];
    size_t k;
    CHECK(brt_mesh_load(mesh_path, &mesh, &err) == BRT_OK, "%s", err.message);
    remove(scratch(scene, "embree.brs"));   /* a new mesh: rebuild the scene file */
    for (k = 0; k < sizeof kinds / sizeof kinds[0]; k++) {
        snprintf(label, sizeof label, "%s, %s rays", name, kinds[k]);
        check_kind(mesh_path, &mesh, kinds[k], label);
    }
    brt_mesh_free(&mesh);
}

/* ===================================================================== */
/* Tests                                                                 */
/* ===================================================================== */

static void check_builtin_scene(const char *name)
{
    char path[512];
    scratch(path, "embree_scene.ply");
    CHECK(run("mkscene %s '%s' --scale 0.4 --seed %llu", name, path,
              (unsigned long long)test_seed()) == 0, "mkscene %s failed", name);
    check_mesh(path, name);
}

static void check_shared_mesh(const char *file)
{
    const char *path = test_shared_mesh(file);
    if (!path) {
        test_skip("shared mesh %s not found (set BRT_SHARED)", file);
        return;
    }
    check_mesh(path, file);
}

static void test_crown(void) { check_builtin_scene("crown"); }
static void test_landscape(void) { check_builtin_scene("landscape"); }
static void test_island(void) { check_builtin_scene("island"); }
static void test_bunny(void) { check_shared_mesh("bunny.obj.gz"); }

/* embree_trace's own contract: build/trace's command line minus the
** batched options (rejected by name, nothing written), statistics in
** trace's JSON, a negative tnear rejected, and rays that batchrt never hits
** (NaN origin, tnear > tfar, zero direction) written as misses. */
static void test_command_line(void)
{
    static const char *const batched_only[] = {"--batched", "--no-proxy", "--rebuild",
                                               "--drop-os-cache"};
    const char *mesh = test_shared_mesh("bunny_tiny.obj");
    const brt_ray invalid[3] = {{{NAN, 0, 5}, {0, 0, -1}, 0, INFINITY},
                                {{0, 1, 5}, {0, 0, -1}, 3, 1},
                                {{0, 1, 5}, {0, 0, 0}, 0, INFINITY}};
    const brt_ray negative = {{0, 1, 5}, {0, 0, -1}, -1, INFINITY};
    char rays[512], hits[512], stats[512], text[2048] = "";
    struct stat st;
    brt_hit *out;
    FILE *f;
    size_t i;
    if (!mesh) {
        test_skip("shared mesh bunny_tiny.obj not found (set BRT_SHARED)");
        return;
    }
    scratch(rays, "cli.rays");
    scratch(hits, "cli.hits");
    scratch(stats, "cli.json");
    remove(hits);
    CHECK(brt_rays_write(rays, invalid, 3, NULL) == BRT_OK, "cannot write %s", rays);
    for (i = 0; i < sizeof batched_only / sizeof batched_only[0]; i++)
        EXPECT(run("embree_trace '%s' '%s' '%s' %s", mesh, rays, hits, batched_only[i]) == 1,
               "%s accepted", batched_only[i]);
    CHECK(stat(hits, &st) != 0, "a rejected command line wrote %s", hits);
    CHECK(run("embree_trace '%s' '%s' '%s' --direct --stats '%s'", mesh, rays, hits, stats) == 0,
          "embree_trace failed on invalid rays");
    CHECK((out = read_hits(hits, 3)) != NULL, "no hits");
    for (i = 0; i < 3; i++)
        EXPECT(out[i].prim == BRT_NO_PRIM && isinf(out[i].t) && out[i].u == 0 && out[i].v == 0,
               "invalid ray %lu: not the miss record", (unsigned long)i);
    free(out);
    if ((f = fopen(stats, "r")) != NULL) {
        text[fread(text, 1, sizeof text - 1, f)] = 0;
        fclose(f);
    }
    EXPECT(strstr(text, "\"rays\": 3,") && strstr(text, "\"mrays_per_second\""),
           "statistics: %s", text);
    CHECK(brt_rays_write(rays, &negative, 1, NULL) == BRT_OK, "cannot write %s", rays);
    EXPECT(run("embree_trace '%s' '%s' '%s'", mesh, rays, hits) == 1, "negative tnear accepted");
}

/* The classifier itself, without Embree: hand-made "Embree" answers that
** are right in each class are accepted, wrong ones are UNEXPLAINED.  A
** unit square of two triangles sharing the diagonal x == y, plus a huge
** far-away triangle for an ill-conditioned t. */
static void test_classifier(void)
{
    static float positions[] = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0,
                                -1e4f, -1e4f, 5, 1e4f, -1e4f, 5, 0, 1e4f, 5};
    static uint32_t indices[] = {0, 1, 2, 0, 2, 3, 4, 5, 6};
    const brt_mesh mesh = {positions, indices, 7, 3};
    const brt_ray diagonal = {{0.5f, 0.5f, 1}, {0, 0, -1}, 0, INFINITY};
    const brt_ray inside = {{0.7f, 0.2f, 1}, {0, 0, -1}, 0, INFINITY};
    const brt_ray at_tnear = {{0.7f, 0.2f, 1}, {0, 0, -1}, 1, INFINITY};
    const brt_ray outside_edge = {{1.0000001f, 0.5f, 1}, {0, 0, -1}, 0, INFINITY};
    const brt_ray outside = {{1.01f, 0.5f, 1}, {0, 0, -1}, 0, INFINITY};
    const brt_ray near_huge = {{0.3f, 0.1f, 4}, {0.6f, 0, 0.8f}, 0, INFINITY};
    const brt_hit miss = {INFINITY, BRT_NO_PRIM, 0, 0};
    brt_hit ours[4], theirs;
    const brt_ray *rays[4] = {&diagonal, &inside, &at_tnear, &near_huge};
    brt_bvh *bvh;
    int i;
    CHECK(brt_bvh_build(positions, indices, 3, NULL, &bvh) == BRT_OK, "BVH build failed");
    for (i = 0; i < 4; i++) {
        brt_hit_clear(&ours[i]);
        brt_bvh_intersect(bvh, rays[i], &ours[i]);
    }
    brt_bvh_free(bvh);
    for (i = 0; i < 4; i++) CHECK(ours[i].prim != BRT_NO_PRIM, "ray %d misses", i);
    CHECK(ours[0].prim == 0 && ours[0].t == 1.0f, "the diagonal tie goes to prim 0");
    /* The diagonal: prim 1 at the same t is a tie, a miss is an edge leak. */
    theirs = ours[0];
    theirs.prim = 1;
    theirs.u = 0.5f;
    theirs.v = 0.0f;
    EXPECT(classify(&mesh, &diagonal, &ours[0], &theirs) == TIE, "shared edge: tie");
    EXPECT(classify(&mesh, &diagonal, &ours[0], &miss) == LEAK, "shared edge: leak");
    /* Inside prim 0, far from every edge: a miss, another prim or another t
    ** is wrong. */
    EXPECT(classify(&mesh, &inside, &ours[1], &ours[1]) == SAME, "same answer");
    EXPECT(classify(&mesh, &inside, &ours[1], &miss) == UNEXPLAINED, "interior leak");
    theirs = ours[1];
    theirs.prim = 1;
    theirs.u = theirs.v = 0.3f;
    EXPECT(classify(&mesh, &inside, &ours[1], &theirs) == UNEXPLAINED, "wrong prim");
    theirs = ours[1];
    theirs.t *= 1.0f + 1e-4f;
    EXPECT(classify(&mesh, &inside, &ours[1], &theirs) == UNEXPLAINED, "wrong t");
    theirs = miss;
    theirs.t = 0.5f;
    theirs.prim = 2;
    theirs.u = theirs.v = 0.3f;
    EXPECT(classify(&mesh, &inside, &ours[1], &theirs) == UNEXPLAINED, "invented hit");
    theirs.prim = 3;
    EXPECT(classify(&mesh, &inside, &ours[1], &theirs) == UNEXPLAINED, "prim out of range");
    /* Just outside the square's open edge x == 1: Embree's hit there is
    ** rounding, a hit a little farther out is invented. */
    theirs = miss;
    theirs.t = 1.0f;
    theirs.prim = 0;
    theirs.u = 0.5f;
    theirs.v = 0.5f;
    EXPECT(classify(&mesh, &outside_edge, &miss, &theirs) == EDGE, "boundary edge hit");
    EXPECT(classify(&mesh, &outside, &miss, &theirs) == UNEXPLAINED, "hit outside");
    /* A hit at t == tnear, which Embree excludes. */
    EXPECT(classify(&mesh, &at_tnear, &ours[2], &miss) == TNEAR, "hit at tnear");
    /* A huge triangle just ahead of the origin: t is ill-conditioned. */
    CHECK(ours[3].prim == 2, "the huge triangle is hit");
    theirs = ours[3];
    theirs.t *= 1.0f + 1e-4f;
    EXPECT(classify(&mesh, &near_huge, &ours[3], &theirs) == ILL_CONDITIONED,
           "ill-conditioned t");
    theirs.t = ours[3].t * 1.5f;
    EXPECT(classify(&mesh, &near_huge, &ours[3], &theirs) == UNEXPLAINED, "t far off");
}

static void test_skipped(void)
{
    test_skip("%s/embree_trace not built (make embree; needs Embree 3, Debian libembree-dev)",
              build_dir());
}

void suite_embree(void)
{
    char path[512];
    struct stat st;
    test_run("embree: the disagreement classifier accepts right and rejects wrong answers",
             test_classifier);
    snprintf(path, sizeof path, "%s/embree_trace", build_dir());
    if (stat(path, &st) != 0) {
        test_run("embree: cross-check against Embree 3", test_skipped);
        return;
    }
    test_run("embree: embree_trace's command line, statistics and invalid rays",
             test_command_line);
    test_run("embree: crown scene, direct == batched == Embree", test_crown);
    test_run("embree: landscape scene, direct == batched == Embree", test_landscape);
    test_run("embree: island scene, direct == batched == Embree", test_island);
    test_run("embree: bunny scan, direct == batched == Embree", test_bunny);
}
