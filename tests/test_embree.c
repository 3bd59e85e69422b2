/*
** tests/test_embree.c -- batchrt against Embree 3, ray by ray (README, "Checking
** against Embree").
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
**   - every ray whose records differ must be explained by hitdiff's
**     referee (examples/lib/referee.c, exact predicates; tested on its own in
**     tests/test_referee.c), or the test fails and prints the verdict;
**   - build/hitdiff --mesh --rays, the user's tool, must come to the same
**     count and exit 0 exactly when nothing is unexplained.
** Then every shared mesh (../shared/data/meshes) gets a sample of each ray
** kind, and hitdiff --mesh must explain every disagreement with Embree.
*/
#include "test.h"
#include "util.h"
#include "batchrt.h"
#include "../examples/lib/rays.h"
#include "../examples/lib/referee.h"

#include <math.h>
#include <stdarg.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

/* Rays per mesh and kind; BRT_EMBREE_RAYS=N overrides it for a longer run
** (with BRT_EMBREE_TABLE=1 the test prints its table even when it passes). */
#define RAYS_PER_KIND 40000
#define MIN_IDENTICAL 0.9999  /* fraction of rays with the same hit/miss and prim */
/* Rays per kind in the sweep over every shared mesh (loading and building
** the largest, 3.5M triangles, dominates its time, not the rays). */
#define SHARED_RAYS_PER_KIND 2500

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
    if (brt_hits_read(path, &hits, &n, NULL, &err) != BRT_OK) {
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

/* Refereeing every disagreement                                        */
/* ===================================================================== */

typedef struct tally {
    uint64_t rays, identical;        /* same hit/miss and same prim */
    uint64_t disagree, classes[EX_CLASSES];
} tally;

/* Every ray of one Embree hit file against batchrt's, through the referee
** (examples/lib/referee.c); each unexplained ray fails the test with the
** referee's verdict (five at most).  The rays of raygen must also agree on
** hit/miss and prim for MIN_IDENTICAL of them; edge rays (make_edge_rays)
** aim at the disagreements, so for them only the referee counts. */
static void compare_with_embree(const char *label, const brt_mesh *mesh, const brt_ray *rays,
                                size_t count, const brt_hit *ours, const brt_hit *theirs,
                                int edge_rays, tally *tl)
{
    ex_verdict verdict;
    size_t i;
    int printed = 0;
    memset(tl, 0, sizeof *tl);
    tl->rays = count;
    for (i = 0; i < count; i++) {
        tl->identical += ours[i].prim == theirs[i].prim;
        if (!ex_hits_disagree(&ours[i], &theirs[i])) continue;
        ex_referee(mesh, &rays[i], &ours[i], &theirs[i], &verdict);
        tl->disagree++;
        tl->classes[verdict.cls]++;
        if (verdict.cls == EX_UNEXPLAINED && printed++ < 5) {
            const brt_ray *r = &rays[i];
            test_fail_at(__FILE__, __LINE__, "%s: ray %lu org (%.9g %.9g %.9g) dir (%.9g %.9g "
                         "%.9g) t [%.9g %.9g]: A = batchrt, B = Embree: %s", label,
                         (unsigned long)i, r->org[0], r->org[1], r->org[2], r->dir[0],
                         r->dir[1], r->dir[2], r->tnear, r->tfar, verdict.text);
        }
    }
    EXPECT(edge_rays || (double)tl->identical >= MIN_IDENTICAL * (double)count,
           "%s: only %llu of %llu rays have the same hit/miss and prim (< %.2f %%)", label,
           (unsigned long long)tl->identical, (unsigned long long)count, 100 * MIN_IDENTICAL);
}

static void print_tally(const char *label, const tally *tl)
{
    int c;
    printf("  %-28s %7llu rays %8.4f %% identical, %llu disagree", label,
           (unsigned long long)tl->rays, 100.0 * (double)tl->identical / (double)tl->rays,
           (unsigned long long)tl->disagree);
    for (c = 0; c < EX_CLASSES; c++)
        if (tl->classes[c])
            printf(", %s %llu", ex_class_id[c], (unsigned long long)tl->classes[c]);
    printf("\n");
}

static int same_bytes(const brt_hit *a, const brt_hit *b, size_t count)
{
    return memcmp(a, b, count * sizeof *a) == 0;
}

/* The user's workflow: build/hitdiff --mesh --rays referees the same rays
** the same way, so it must exit 0 exactly when nothing here is
** unexplained, and count the same disagreements. */
static void expect_hitdiff_verdict(const char *label, const char *mesh, const char *rays,
                                   const char *ours, const char *theirs, const tally *tl)
{
    char line[128], log[512];
    const int expected = tl->classes[EX_UNEXPLAINED] ? 1 : 0;
    const int status = run("hitdiff '%s' '%s' --mesh '%s' --rays '%s'", ours, theirs, mesh,
                           rays);
    unsigned char *out = tu_slurp(scratch(log, "embree.log"), NULL);
    snprintf(line, sizeof line, "%llu disagreeing rays of %llu",
             (unsigned long long)tl->disagree, (unsigned long long)tl->rays);
    EXPECT(status == expected && out && strstr((char *)out, line),
           "%s: hitdiff %s %s: exit status %d, expected %d and '%s' in:\n%s", label, ours,
           theirs, status, expected, line, out ? (char *)out : "(no output)");
    free(out);
}

/* The hardest rays for a ray/triangle test that is not watertight: from
** random points of the mesh's box (grown by half its size) at random
** points of triangle edges (one ray in four at a vertex), rounded to
** float, so they cross the edge within a few ulps. */
static void make_edge_rays(const brt_mesh *mesh, brt_ray *rays, size_t count, uint64_t *rng)
{
    float lo[3], hi[3];
    size_t i;
    int k;
    brt_mesh_bounds(mesh, lo, hi);
    for (i = 0; i < count; i++) {
        const uint32_t prim = (uint32_t)(brt_random_u64(rng) % mesh->triangle_count);
        const uint32_t *tri = mesh->indices + 3 * (size_t)prim;
        const int corner = (int)(brt_random_u64(rng) % 3);
        const float *from = mesh->positions + 3 * (size_t)tri[corner];
        const float *to = mesh->positions + 3 * (size_t)tri[(corner + 1) % 3];
        const float s = brt_random_u64(rng) % 4 == 0 ? 0.0f : brt_random_float(rng);
        for (k = 0; k < 3; k++) {
            const float target = from[k] + s * (to[k] - from[k]);
            const float size = hi[k] - lo[k];
            rays[i].org[k] = lo[k] - 0.5f * size + 2.0f * size * brt_random_float(rng);
            rays[i].dir[k] = target - rays[i].org[k];
        }
        rays[i].tnear = 0.0f;
        rays[i].tfar = INFINITY;
    }
}

static int write_edge_rays(const brt_mesh *mesh, const char *path)
{
    const size_t count = (size_t)rays_per_kind();
    uint64_t rng = test_seed();
    brt_ray *rays = malloc(count * sizeof *rays);
    brt_result r;
    if (!rays) return 0;
    make_edge_rays(mesh, rays, count, &rng);
    r = brt_rays_write(path, rays, count, NULL);
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
             "--batched --point-tris 4000 --proxy-res 32 --memory 256K --scene '%s'",
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
            expect_hitdiff_verdict(label, mesh_path, rays_path, direct_path, embree_path,
                                   &tl[m]);
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
/* Every shared mesh through hitdiff --mesh                              */
/* ===================================================================== */

/* SHARED_RAYS_PER_KIND rays of each kind, kind after kind: camera, random
** and bounce (examples/lib/rays.c, as build/raygen makes them), then edge. */
static int make_sample_rays(const brt_mesh *mesh, const brt_bvh *bvh, brt_ray *rays)
{
    const size_t n = SHARED_RAYS_PER_KIND;
    const uint32_t width = (uint32_t)ceil(sqrt((double)n));
    uint64_t rng = test_seed();
    float lo[3], hi[3];
    ex_camera cam;
    brt_mesh_bounds(mesh, lo, hi);
    ex_camera_fit(&cam, lo, hi, width, (uint32_t)((n + width - 1) / width));
    ex_rays_camera(&cam, rays, n, &rng);
    ex_rays_random(lo, hi, rays + n, n, &rng);
    if (!ex_rays_bounce(mesh, bvh, &cam, rays + 2 * n, n, &rng)) return 0;
    make_edge_rays(mesh, rays + 3 * n, n, &rng);
    return 1;
}

/* The sample rays and batchrt's hits for them (brt_bvh_intersect, which
** writes the bytes of trace --direct) as files in the scratch directory. */
static int write_sample(const brt_mesh *mesh, const char *rays_path, const char *hits_path)
{
    const size_t count = 4 * SHARED_RAYS_PER_KIND;
    brt_ray *rays = malloc(count * sizeof *rays);
    brt_hit *hits = malloc(count * sizeof *hits);
    brt_bvh *bvh = NULL;
    int ok = rays && hits
             && brt_bvh_build(mesh->positions, mesh->indices, mesh->triangle_count, NULL, &bvh)
                    == BRT_OK
             && make_sample_rays(mesh, bvh, rays);
    size_t i;
    for (i = 0; ok && i < count; i++) {
        brt_hit_clear(&hits[i]);
        brt_bvh_intersect(bvh, &rays[i], &hits[i]);
    }
    ok = ok && brt_rays_write(rays_path, rays, count, NULL) == BRT_OK
         && brt_hits_write(hits_path, hits, count, NULL) == BRT_OK;
    brt_bvh_free(bvh);
    free(rays);
    free(hits);
    return ok;
}

/* hitdiff's table and the first unexplained lines of its CSV, for a
** failure message (malloc'd). */
static char *hitdiff_report(const char *csv_path)
{
    char log[512], *out = (char *)tu_slurp(scratch(log, "embree.log"), NULL);
    char *csv = (char *)tu_slurp(csv_path, NULL), *line = csv, *report;
    size_t size = (out ? strlen(out) : 0) + 5 * 1100 + 1, used;
    int shown = 0;
    if (!(report = malloc(size))) return NULL;
    used = (size_t)snprintf(report, size, "%s", out ? out : "(no output)\n");
    while (line && *line && shown < 5) {
        char *end = strchr(line, '\n');
        const size_t len = end ? (size_t)(end - line) : strlen(line);
        if (strstr(line, ",unexplained,") && strstr(line, ",unexplained,") < line + len
            && len < 1024) {
            used += (size_t)snprintf(report + used, size - used, "%.*s\n", (int)len, line);
            shown++;
        }
        line = end ? end + 1 : NULL;
    }
    free(out);
    free(csv);
    return report;
}

/* One shared mesh: batchrt's hits against Embree's (default and --robust)
** on the sample, refereed by build/hitdiff --mesh; every disagreement must
** be explained.  Rays 0.., 2500.., 5000.., 7500.. are camera, random,
** bounce and edge rays. */
static void check_shared_referee(const char *file)
{
    static const char *const modes[2] = {"", "--robust"};
    const char *path = test_shared_mesh(file);
    char rays_path[512], ours[512], theirs[512], csv[512];
    brt_mesh mesh;
    brt_error err;
    int m, ok;
    if (!path) {
        test_skip("shared mesh %s not found (set BRT_SHARED)", file);
        return;
    }
    CHECK(brt_mesh_load(path, &mesh, &err) == BRT_OK, "%s", err.message);
    ok = write_sample(&mesh, scratch(rays_path, "sample.rays"), scratch(ours, "sample.hits"));
    brt_mesh_free(&mesh);
    CHECK(ok, "%s: cannot make the sample rays and hits", file);
    scratch(theirs, "sample_embree.hits");
    scratch(csv, "sample.csv");
    for (m = 0; m < 2; m++) {
        int status;
        CHECK(run("embree_trace '%s' '%s' '%s' %s", path, rays_path, theirs, modes[m]) == 0,
              "%s: embree_trace %s failed", file, modes[m]);
        status = run("hitdiff '%s' '%s' --mesh '%s' --rays '%s' --explain '%s'", ours, theirs,
                     path, rays_path, csv);
        if (status != 0 || getenv("BRT_EMBREE_TABLE")) {
            char *report = hitdiff_report(csv);
            printf("%s, Embree %s:\n%s", file, m ? "--robust" : "default", report ? report : "");
            free(report);
        }
        EXPECT(status == 0, "%s: hitdiff --mesh against Embree %s: exit status %d (above)", file,
               modes[m], status);
    }
}

/* ===================================================================== */
/* Tests                                                                 */
/* ===================================================================== */

/* scale: about 40 thousand triangles of the scene */
static void check_builtin_scene(const char *name, const char *scale)
{
    char path[512];
    scratch(path, "embree_scene.ply");
    CHECK(run("mkscene %s '%s' --scale %s --seed %llu", name, path, scale,
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

/* An instanced scene (mkscene's .pbrt: one Object per prototype, an
** ObjectInstance per instance): trace --direct == --batched byte for byte,
** embree_trace with one rtcInstance per instance, and hitdiff --mesh
** explains every difference, the transform's rounding included. */
static void check_instanced_scene(const char *name)
{
    static const char *const kinds[3] = {"camera", "random", "bounce"};
    char scene[512], rays[512], d[512], b[512], e[512], log[512], brs[512];
    int k;
    scratch(scene, "inst.pbrt");
    scratch(rays, "inst.rays");
    scratch(d, "inst_d.hits");
    scratch(b, "inst_b.hits");
    scratch(e, "inst_e.hits");
    scratch(brs, "inst.brs");
    CHECK(run("mkscene %s '%s' --scale 0.3 --seed %llu", name, scene,
              (unsigned long long)test_seed()) == 0, "mkscene %s .pbrt failed", name);
    for (k = 0; k < 3; k++) {
        unsigned char *hd, *hb, *out;
        size_t nd = 0, nb = 0;
        CHECK(run("raygen '%s' '%s' --kind %s --count 40000 --seed %d", scene, rays, kinds[k], k + 1)
              == 0, "raygen %s", kinds[k]);
        CHECK(run("trace '%s' '%s' '%s' --direct", scene, rays, d) == 0, "trace --direct");
        CHECK(run("trace '%s' '%s' '%s' --batched --point-tris 3000 --memory 300K --scene '%s' "
                  "--rebuild", scene, rays, b, brs) == 0, "trace --batched");
        CHECK(run("embree_trace '%s' '%s' '%s'", scene, rays, e) == 0, "embree_trace");
        hd = tu_slurp(d, &nd);
        hb = tu_slurp(b, &nb);
        EXPECT(hd && hb && nd == nb && memcmp(hd, hb, nd) == 0, "%s %s: direct and batched differ",
               name, kinds[k]);
        free(hd);
        free(hb);
        EXPECT(run("hitdiff '%s' '%s' --mesh '%s' --rays '%s'", d, e, scene, rays) == 0,
               "%s %s: hitdiff --mesh left differences unexplained", name, kinds[k]);
        out = tu_slurp(scratch(log, "embree.log"), NULL);
        EXPECT(out && strstr((char *)out, "EXPLAINED: all"), "%s %s: %s", name, kinds[k],
               out ? (char *)out : "(no output)");
        if (out) printf("  embree: %s %s: %s", name, kinds[k], strstr((char *)out, "EXPLAINED") ? strstr((char *)out, "EXPLAINED") : "\n");
        free(out);
    }
}

static void test_instanced_landscape(void) { check_instanced_scene("landscape"); }
static void test_instanced_island(void) { check_instanced_scene("island"); }

static void test_crown(void) { check_builtin_scene("crown", "0.4"); }
static void test_landscape(void) { check_builtin_scene("landscape", "0.006"); }
static void test_island(void) { check_builtin_scene("island", "0.01"); }
static void test_bunny(void) { check_shared_mesh("bunny.obj.gz"); }
static void test_referee_bunny_tiny(void) { check_shared_referee("bunny_tiny.obj"); }
static void test_referee_bunny(void) { check_shared_referee("bunny.obj.gz"); }
static void test_referee_dragon(void) { check_shared_referee("dragon.obj.gz"); }
static void test_referee_bmw(void) { check_shared_referee("bmw_m6.obj.gz"); }
static void test_referee_oahu(void) { check_shared_referee("fg_oahu.obj.gz"); }
static void test_referee_crown(void) { check_shared_referee("crown.obj.gz"); }

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

static void test_skipped(void)
{
    test_skip("%s/embree_trace not built (make embree; needs Embree 3, Debian libembree-dev)",
              build_dir());
}

void suite_embree(void)
{
    char path[512];
    struct stat st;
    snprintf(path, sizeof path, "%s/embree_trace", build_dir());
    if (stat(path, &st) != 0 && !test_listing()) {
        test_run("embree: cross-check against Embree 3", test_skipped);
        return;
    }
    test_run("embree: embree_trace's command line, statistics and invalid rays",
             test_command_line);
    test_run("embree: crown scene, direct == batched == Embree", test_crown);
    test_run("embree: landscape scene, direct == batched == Embree", test_landscape);
    test_run("embree: island scene, direct == batched == Embree", test_island);
    test_run("embree: bunny scan, direct == batched == Embree", test_bunny);
    test_run("embree: instanced landscape (pbrt), direct == batched, Embree refereed",
             test_instanced_landscape);
    test_run("embree: instanced island (pbrt), direct == batched, Embree refereed",
             test_instanced_island);
    test_run("embree: hitdiff --mesh explains every disagreement, bunny_tiny",
             test_referee_bunny_tiny);
    test_run("embree: hitdiff --mesh explains every disagreement, bunny", test_referee_bunny);
    test_run("embree: hitdiff --mesh explains every disagreement, dragon", test_referee_dragon);
    test_run("embree: hitdiff --mesh explains every disagreement, bmw_m6", test_referee_bmw);
    test_run("embree: hitdiff --mesh explains every disagreement, fg_oahu", test_referee_oahu);
    test_run("embree: hitdiff --mesh explains every disagreement, crown", test_referee_crown);
}
