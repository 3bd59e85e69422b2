/*
** tests/test_batched.c -- the out-of-core batched traversal against the
** direct mode (one BVH over the whole mesh in memory), hit by hit, byte
** for byte: across batch sizes down to one triangle per batching point,
** memory limits down to less than one batching point, proxies on and off,
** proxy resolutions 2 to 256, and rays in flight from 1 up.  Also: the
** geometry cache's budget, what proxies may and may not change, the scene
** file's reuse and its errors, and injected read faults.
*/
#include "test.h"
#include "util.h"
#include "fuzz/targets.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

/* ---- fixtures ------------------------------------------------------------ */

typedef struct fixture {
    tu_scene scene;
    brt_ray *rays;
    brt_hit *direct;          /* the reference hits */
    size_t count;
} fixture;

/* The reference: direct-mode hits of the fixture's rays. */
static int fixture_direct(fixture *f)
{
    brt_bvh *bvh = NULL;
    size_t i;
    if (brt_bvh_build(f->scene.pos, f->scene.idx, f->scene.tcount, NULL, &bvh) != BRT_OK) return 0;
    for (i = 0; i < f->count; i++) {
        brt_hit_clear(&f->direct[i]);
        brt_bvh_intersect(bvh, &f->rays[i], &f->direct[i]);
    }
    brt_bvh_free(bvh);
    return 1;
}

/* Rays of all four kinds, and their direct-mode hits. */
static int fixture_rays(fixture *f, size_t per_kind, uint64_t seed)
{
    float lo[3], hi[3];
    uint64_t st = seed;
    size_t i;
    int kind;
    tu_scene_bounds(&f->scene, lo, hi);
    f->count = per_kind * TU_RAY_KINDS;
    f->rays = malloc(f->count * sizeof *f->rays);
    f->direct = malloc(f->count * sizeof *f->direct);
    for (kind = 0; kind < TU_RAY_KINDS; kind++)
        for (i = 0; i < per_kind; i++)
            tu_make_ray(&f->scene, lo, hi, kind, &st, &f->rays[(size_t)kind * per_kind + i]);
    return fixture_direct(f);
}

static void fixture_free(fixture *f)
{
    tu_scene_free(&f->scene);
    free(f->rays);
    free(f->direct);
}

static brt_scene *build_scene(const tu_scene *s, uint32_t point_tris, uint32_t res, const char *path)
{
    return tu_build_scene(s, point_tris, res, 0, path);
}

/* Traces the fixture's rays in batched mode and compares every hit. */
static int trace_matches(const fixture *f, brt_scene *scene, const brt_trace_options *opt,
                         brt_stats *stats, const char *what)
{
    brt_hit *hits = malloc(f->count * sizeof *hits);
    brt_error err;
    size_t i;
    int ok = 1;
    brt_result r = brt_scene_trace(scene, opt, f->rays, f->count, hits, stats, &err);
    if (r != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s: trace: %s", what, err.message);
        ok = 0;
    }
    for (i = 0; ok && i < f->count; i++)
        if (memcmp(&hits[i], &f->direct[i], sizeof *hits) != 0) {
            const brt_ray *ray = &f->rays[i];
            test_fail_at(__FILE__, __LINE__, "%s: ray %zu (%s, o %a %a %a d %a %a %a): batched t=%a "
                         "prim=%u, direct t=%a prim=%u", what, i, tu_kind_name[i * TU_RAY_KINDS / f->count],
                         ray->org[0], ray->org[1], ray->org[2], ray->dir[0], ray->dir[1], ray->dir[2],
                         hits[i].t, (unsigned)hits[i].prim, f->direct[i].t, (unsigned)f->direct[i].prim);
            ok = 0;
        }
    free(hits);
    return ok;
}

/* ---- batched == direct --------------------------------------------------- */

/* Which batching points a ray visits does not depend on the schedule: its
** walk goes in key order, and a point the proxy culls holds no hit that
** would change the closest hit so far.  So without proxies, or with them
** and every ray queued (paper_scheduler), the visits are the same under
** every limit; intersecting at once in memory (the default) skips the
** proxy there, so it visits at least what the proxies leave and at most
** what no proxy culls. */
static void check_visits(const brt_stats *stats, const brt_trace_options *opt,
                         const brt_stats paper_runs[2], const char *what)
{
    const uint64_t paper[2] = {paper_runs[0].visits, paper_runs[1].visits};
    uint64_t v = stats->visits;
    int proxy = !opt->no_proxy;
    EXPECT(!opt->paper_scheduler || stats->resident_visits == 0,
           "%s: %llu resident visits while queueing them all", what,
           (unsigned long long)stats->resident_visits);
    if (!proxy || opt->paper_scheduler)
        EXPECT(v == paper[proxy], "%s: %llu visits, not %llu", what, (unsigned long long)v,
               (unsigned long long)paper[proxy]);
    else
        EXPECT(paper[1] <= v && v <= paper[0], "%s: %llu visits, outside %llu..%llu", what,
               (unsigned long long)v, (unsigned long long)paper[1], (unsigned long long)paper[0]);
}

/* One scene, every memory limit, proxy setting and queueing policy; checks
** the budget and that proxies only ever remove work. */
static void sweep_settings(const fixture *f, uint32_t point_tris, uint32_t res, const char *name)
{
    brt_scene *scene = build_scene(&f->scene, point_tris, res, tu_scratch(name));
    brt_trace_options opt;
    brt_stats all, none, stats, paper[2];   /* paper: the paper's scheduler, no limit */
    char what[200];
    int proxy, setting;
    uint64_t limits[3], largest = 0;
    int l;
    if (!scene) return;
    memset(&opt, 0, sizeof opt);
    opt.paper_scheduler = 1;
    for (proxy = 0; proxy < 2; proxy++) {
        opt.no_proxy = !proxy;
        snprintf(what, sizeof what, "%s, batch %u, res %u, no limit, proxies %s, all queued", name,
                 point_tris, res, proxy ? "on" : "off");
        if (!trace_matches(f, scene, &opt, &paper[proxy], what)) goto done;
    }
    opt.paper_scheduler = 0;
    opt.no_proxy = 1;
    snprintf(what, sizeof what, "%s, batch %u, res %u, no limit, no proxy", name, point_tris, res);
    if (!trace_matches(f, scene, &opt, &none, what)) goto done;
    opt.no_proxy = 0;
    snprintf(what, sizeof what, "%s, batch %u, res %u, no limit, proxies", name, point_tris, res);
    if (!trace_matches(f, scene, &opt, &all, what)) goto done;
    /* Proxies only cull: never more visits, nor (with every blob kept)
    ** more loads.  (Under a tight limit the schedule changes, so loads are
    ** compared only without one.) */
    EXPECT(paper[1].visits <= paper[0].visits, "%s: proxies increased visits %llu > %llu", what,
           (unsigned long long)paper[1].visits, (unsigned long long)paper[0].visits);
    EXPECT(paper[1].batch_loads <= paper[0].batch_loads, "%s: proxies increased loads", what);
    /* With room for every blob the default scheduler leaves the proxies
    ** alone (they could only put loads off); the paper's consults them. */
    EXPECT(all.proxy_tests == 0 && all.batch_loads == none.batch_loads,
           "%s: %llu proxy tests with room for everything", what, (unsigned long long)all.proxy_tests);
    EXPECT(paper[1].proxy_tests > 0, "%s: the paper's scheduler tested no proxy", what);
    EXPECT(all.proxy_tests >= all.proxy_culled, "%s: more culls than tests", what);
    EXPECT(none.proxy_tests == 0 && none.proxy_bytes == 0, "%s: --no-proxy ran proxy tests", what);
    EXPECT(none.rays == f->count && all.batching_points == brt_scene_point_count(scene),
           "%s: statistics count %llu rays", what, (unsigned long long)none.rays);
    limits[0] = 1;                                   /* less than one batching point */
    limits[1] = none.geometry_bytes / 2 + 1;          /* half */
    limits[2] = none.cache_peak_bytes + all.proxy_bytes; /* everything (page-rounded) + proxies */
    for (l = 0; l < 3 && !test_failed(); l++)
        for (setting = 0; setting < 4 && !test_failed(); setting++) {
            uint64_t budget;
            proxy = setting & 1;
            opt.memory_limit = limits[l];
            opt.no_proxy = !proxy;
            opt.paper_scheduler = setting >> 1;
            snprintf(what, sizeof what, "%s, batch %u, res %u, limit %llu, proxies %s%s", name,
                     point_tris, res, (unsigned long long)limits[l], proxy ? "on" : "off",
                     opt.paper_scheduler ? ", all queued" : "");
            if (!trace_matches(f, scene, &opt, &stats, what)) break;
            check_visits(&stats, &opt, paper, what);
            budget = limits[l] > stats.proxy_bytes ? limits[l] - stats.proxy_bytes : 0;
            /* Under the 1-byte limit (first) every blob is held alone, so
            ** the peaks there give the largest blob any ray loads (without
            ** proxies every reached point is loaded). */
            if (l == 0 && stats.cache_peak_bytes > largest) largest = stats.cache_peak_bytes;
            /* Never over budget, except one blob alone that is larger (the
            ** cache checks that itself; here the statistics say it too). */
            EXPECT(stats.cache_peak_bytes <= (budget > largest ? budget : largest) &&
                   (stats.oversized_loads == 0 || largest > budget),
                   "%s: cache peak %llu over budget %llu and over the largest blob %llu", what,
                   (unsigned long long)stats.cache_peak_bytes, (unsigned long long)budget,
                   (unsigned long long)largest);
            EXPECT(l != 0 || stats.oversized_loads == stats.batch_loads,
                   "%s: a 1-byte budget must make every load oversized", what);
            EXPECT(l != 2 || stats.batch_loads == paper[proxy && stats.proxy_tests > 0].batch_loads,
                   "%s: with room for everything, each batching point loads once", what);
            EXPECT(stats.disk_bytes_read >= stats.batch_loads, "%s: loads without reads", what);
            /* Loading time is a part of the trace's, and only loads take it. */
            EXPECT((stats.load_seconds > 0) == (stats.batch_loads > 0) &&
                   stats.load_seconds <= stats.seconds,
                   "%s: %llu loads took %g s of a %g s trace", what,
                   (unsigned long long)stats.batch_loads, stats.load_seconds, stats.seconds);
        }
done:
    brt_scene_close(scene);
}

static void test_soup_batch_sizes(void)
{
    static const uint32_t batch[] = {1, 7, 1000, 100000};
    fixture f;
    size_t b;
    uint64_t st = test_seed();
    memset(&f, 0, sizeof f);
    tu_random_soup(&f.scene, &st, 3000, 0.03f);
    CHECK(fixture_rays(&f, 500, st), "direct BVH build failed");
    for (b = 0; b < sizeof batch / sizeof batch[0] && !test_failed(); b++)
        sweep_settings(&f, batch[b], 16, "soup");
    fixture_free(&f);
}

static void test_soup_resolutions(void)
{
    fixture f;
    uint32_t res;
    uint64_t st = test_seed() + 1;
    memset(&f, 0, sizeof f);
    tu_random_soup(&f.scene, &st, 2000, 0.05f);
    CHECK(fixture_rays(&f, 400, st), "direct BVH build failed");
    for (res = 2; res <= 256 && !test_failed(); res *= 2) sweep_settings(&f, 150, res, "soup-res");
    fixture_free(&f);
}

/* exact_proxies, the analysis mode: a perfect proxy culls every visit a
** voxel proxy culls and more (a voxel miss proves a triangle miss), and
** never one with a hit (the hits stay the direct ones). */
static void test_exact_proxies(void)
{
    fixture f;
    brt_scene *scene;
    brt_trace_options opt;
    brt_stats voxel, exact, limited;
    uint64_t st = test_seed() + 2;
    memset(&f, 0, sizeof f);
    tu_random_soup(&f.scene, &st, 2000, 0.05f);
    CHECK(fixture_rays(&f, 400, st), "direct BVH build failed");
    scene = build_scene(&f.scene, 150, 16, tu_scratch("exact.brs"));
    memset(&opt, 0, sizeof opt);
    opt.paper_scheduler = 1;   /* the paper's scheduler: every visit meets a proxy */
    if (scene && trace_matches(&f, scene, &opt, &voxel, "voxel proxies")) {
        opt.exact_proxies = 1;
        if (trace_matches(&f, scene, &opt, &exact, "exact proxies"))
            EXPECT(exact.visits < voxel.visits && exact.proxy_culled > voxel.proxy_culled &&
                   exact.disk_bytes_read <= voxel.disk_bytes_read,
                   "exact proxies: %llu visits, %llu culled; voxel proxies: %llu, %llu",
                   (unsigned long long)exact.visits, (unsigned long long)exact.proxy_culled,
                   (unsigned long long)voxel.visits, (unsigned long long)voxel.proxy_culled);
        opt.paper_scheduler = 0;
        opt.memory_limit = exact.geometry_bytes / 3;
        trace_matches(&f, scene, &opt, &limited, "exact proxies, a third of the geometry");
    }
    brt_scene_close(scene);
    fixture_free(&f);
}

/* The limits of the top-level walk and of the proxy test are inclusive: a
** ray whose closest hit so far is at t must still be queued at a batching
** point that holds a hit at the same t with a lower prim (the one ordering
** rule of closest hits).  Two triangles in the plane z = 0 meet the ray at
** t = 10 exactly: prim 0 in batching point B (with a flat filler far at
** -x), prim 2 in A (with a filler at +x rising to z = 5).  The centroids'
** x order (-10, -1 | 0.67, 10) puts them in different points at 2
** triangles each.  Ray 0 starts at tnear = 0: it enters A's box first (at
** t = 5) and B's padded box a little before t = 10.  Ray 1 starts at
** tnear = 10, on the plane: both boxes are entered exactly at t = 10, the
** hit's t, and the walk takes the lower id first; the scene and its mirror
** image (x -> -x) each put one of A and B first.  When A comes first the
** ray meets prim 2, then must visit B: an exclusive limit (top-level walk
** or proxy) would cull B and return prim 2. */
static void equal_t_tie(float mirror)
{
    static const float tri[4][3][3] = {
        {{-2, 0, 0}, {1, 0, 0}, {-2, 2, 0}},          /* 0: B, hit at t = 10 */
        {{-10.5f, 0, 0}, {-9.5f, 0, 0}, {-10, 1, 0}},  /* 1: B's filler */
        {{0, 0, 0}, {2, 0, 0}, {0, 2, 0}},             /* 2: A, hit at t = 10 */
        {{9.5f, 0, 0}, {10.5f, 0, 0}, {10, 1, 5}}};    /* 3: A's filler, tall */
    fixture f;
    brt_scene *scene;
    int t, c, setting;
    size_t i;
    memset(&f, 0, sizeof f);
    for (t = 0; t < 4; t++) {
        uint32_t v[3];
        for (c = 0; c < 3; c++)
            v[c] = tu_add_vertex(&f.scene, mirror * tri[t][c][0], tri[t][c][1], tri[t][c][2]);
        tu_add_triangle(&f.scene, v[0], v[1], v[2]);
    }
    f.count = 2;
    f.rays = calloc(2, sizeof *f.rays);
    f.direct = malloc(2 * sizeof *f.direct);
    CHECK(f.rays && f.direct, "out of memory");
    for (i = 0; i < 2; i++) {
        f.rays[i].org[0] = mirror * 0.25f;
        f.rays[i].org[1] = 0.25f;
        f.rays[i].org[2] = 10;
        f.rays[i].dir[2] = -1;
        f.rays[i].tnear = i == 0 ? 0.0f : 10.0f;
        f.rays[i].tfar = INFINITY;
    }
    CHECK(fixture_direct(&f), "direct BVH build failed");
    for (i = 0; i < 2; i++)
        CHECK(f.direct[i].t == 10 && f.direct[i].prim == 0,
              "direct, ray %zu: t=%a prim=%u, expected 10 and prim 0", i, f.direct[i].t,
              (unsigned)f.direct[i].prim);
    scene = build_scene(&f.scene, 2, 16, tu_scratch("tie.brs"));
    for (setting = 0; scene && setting < 6 && !test_failed(); setting++) {
        static const char *const names[3] = {"no proxies", "voxel proxies", "exact proxies"};
        brt_trace_options opt;
        brt_stats stats;
        char what[96];
        memset(&opt, 0, sizeof opt);
        opt.no_proxy = setting % 3 == 0;
        opt.exact_proxies = setting % 3 == 2;
        opt.paper_scheduler = setting / 3;
        opt.memory_limit = 1;   /* below one blob: B is on disk when the ray reaches it */
        snprintf(what, sizeof what, "x %+g, %s, %s scheduler", mirror, names[setting % 3],
                 setting / 3 ? "paper's" : "batchrt's");
        if (trace_matches(&f, scene, &opt, &stats, what))
            EXPECT(stats.batching_points == 2 && stats.visits == 4,
                   "%s: %llu batching points, %llu visits (expected 2 and 4: A and B per ray)", what,
                   (unsigned long long)stats.batching_points, (unsigned long long)stats.visits);
    }
    brt_scene_close(scene);
    fixture_free(&f);
}

static void test_equal_t_tie(void)
{
    equal_t_tie(1.0f);
    if (!test_failed()) equal_t_tie(-1.0f);
}

/* Scales from 1e-3 to 1e5 and an offset far from the origin. */
static void test_soup_scales(void)
{
    static const float scale[] = {1e-3f, 1e5f}, offset[] = {0.0f, 3e4f};
    size_t i;
    for (i = 0; i < 2 && !test_failed(); i++) {
        fixture f;
        uint64_t st = test_seed() + 2 + i;
        memset(&f, 0, sizeof f);
        tu_random_soup(&f.scene, &st, 1500, 0.04f);
        tu_scene_transform(&f.scene, scale[i], offset[i] * scale[i]);
        CHECK(fixture_rays(&f, 300, st), "direct BVH build failed");
        sweep_settings(&f, 40, 64, "soup-scaled");
        fixture_free(&f);
    }
}

/* Axis-aligned triangles: batching points of one triangle have flat
** boxes (zero thickness), which the walk must still enter. */
static void test_flat_boxes(void)
{
    fixture f;
    uint64_t st = test_seed() + 8;
    int i, j, axis;
    memset(&f, 0, sizeof f);
    for (axis = 0; axis < 3; axis++)
        for (i = 0; i < 6; i++)
            for (j = 0; j < 6; j++) {
                float p[3][3];
                uint32_t v[3];
                int c;
                for (c = 0; c < 3; c++) {
                    p[c][axis] = 0.125f * (float)(i + 1);
                    p[c][(axis + 1) % 3] = 0.125f * (float)j + (c == 1 ? 0.125f : 0.0f);
                    p[c][(axis + 2) % 3] = 0.125f * (float)i + (c == 2 ? 0.125f : 0.0f);
                    v[c] = tu_add_vertex(&f.scene, p[c][0], p[c][1], p[c][2]);
                }
                tu_add_triangle(&f.scene, v[0], v[1], v[2]);
            }
    CHECK(fixture_rays(&f, 500, st), "direct BVH build failed");
    sweep_settings(&f, 1, 8, "flat");
    if (!test_failed()) sweep_settings(&f, 3, 4, "flat");
    fixture_free(&f);
}

/* A shared mesh loaded from disk. */
static void compare_shared_mesh(const char *name, uint32_t point_tris, size_t per_kind)
{
    const char *path = test_shared_mesh(name);
    brt_mesh mesh;
    brt_error err;
    fixture f;
    if (!path) {
        test_skip("../shared/data/meshes/%s not present", name);
        return;
    }
    CHECK(brt_mesh_load(path, &mesh, &err) == BRT_OK, "%s", err.message);
    memset(&f, 0, sizeof f);
    f.scene.pos = mesh.positions;
    f.scene.idx = mesh.indices;
    f.scene.vcount = f.scene.vcap = mesh.vertex_count;
    f.scene.tcount = f.scene.tcap = mesh.triangle_count;
    CHECK(fixture_rays(&f, per_kind, test_seed()), "direct BVH build failed");
    sweep_settings(&f, point_tris, 64, name);
    fixture_free(&f);
}

static void test_bunny_tiny(void) { compare_shared_mesh("bunny_tiny.obj", 100, 2000); }
static void test_bunny(void) { compare_shared_mesh("bunny.obj.gz", 5000, 5000); }

/* ---- the stream: any number of rays in flight ---------------------------- */

typedef struct stream_state {
    const fixture *f;
    brt_hit *hits;
    size_t next, finished, bad_normals;
    uint64_t visits;           /* the per-ray counts, added up */
    size_t batch;              /* rays handed out per call at most */
} stream_state;

static size_t stream_next(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    stream_state *s = user;
    size_t n = 0;
    while (n < max && n < s->batch && s->next < s->f->count) {
        rays[n] = s->f->rays[s->next];
        tags[n++] = s->next++;
    }
    return n;
}

/* Records the hit, and checks the normal against the mesh's triangle. */
static void stream_finished(void *user, const brt_ray *ray, const brt_hit *hit,
                            const float normal[3], uint32_t visits, uint64_t tag)
{
    stream_state *s = user;
    float want[3] = {0, 0, 0};
    (void)ray;
    s->hits[tag] = *hit;
    s->finished++;
    s->visits += visits;
    if (hit->prim != BRT_NO_PRIM) {
        const float *v0 = tu_vertex(&s->f->scene, hit->prim, 0), *v1 = tu_vertex(&s->f->scene, hit->prim, 1),
                    *v2 = tu_vertex(&s->f->scene, hit->prim, 2);
        float e1[3], e2[3];
        int a;
        for (a = 0; a < 3; a++) {
            e1[a] = v1[a] - v0[a];
            e2[a] = v2[a] - v0[a];
        }
        want[0] = e1[1] * e2[2] - e1[2] * e2[1];
        want[1] = e1[2] * e2[0] - e1[0] * e2[2];
        want[2] = e1[0] * e2[1] - e1[1] * e2[0];
    }
    if (memcmp(want, normal, sizeof want) != 0) s->bad_normals++;
}

static void test_rays_in_flight(void)
{
    static const uint32_t in_flight[] = {1, 7, 64};
    fixture f;
    brt_scene *scene;
    uint64_t st = test_seed() + 7;
    size_t i;
    memset(&f, 0, sizeof f);
    tu_random_soup(&f.scene, &st, 800, 0.05f);
    CHECK(fixture_rays(&f, 100, st), "direct BVH build failed");
    scene = build_scene(&f.scene, 50, 32, tu_scratch("stream.brs"));
    for (i = 0; scene && i < 3 && !test_failed(); i++) {
        brt_trace_options opt;
        brt_ray_source source;
        stream_state s;
        brt_stats stats;
        brt_error err;
        memset(&opt, 0, sizeof opt);
        opt.rays_in_flight = in_flight[i];
        opt.memory_limit = 64 << 10;
        s.f = &f;
        s.hits = malloc(f.count * sizeof *s.hits);
        s.next = s.finished = s.bad_normals = 0;
        s.visits = 0;
        s.batch = 3;
        source.next_rays = stream_next;
        source.finished = stream_finished;
        source.user = &s;
        EXPECT(brt_scene_trace_stream(scene, &opt, &source, &stats, &err) == BRT_OK, "%s", err.message);
        EXPECT(s.visits == stats.visits && s.visits > 0,
               "per-ray visits add up to %llu, statistics say %llu", (unsigned long long)s.visits,
               (unsigned long long)stats.visits);
        EXPECT(s.finished == f.count, "%zu of %zu rays finished", s.finished, f.count);
        EXPECT(s.bad_normals == 0, "%zu hits came with a wrong normal", s.bad_normals);
        EXPECT(memcmp(s.hits, f.direct, f.count * sizeof *s.hits) == 0,
               "%u rays in flight: hits differ from direct", in_flight[i]);
        free(s.hits);
    }
    brt_scene_close(scene);
    fixture_free(&f);
}

/* ---- the scheduler's rule -------------------------------------------- */

/* Seven unit triangles 10 apart, one per batching point, and vertical rays
** onto them: queue lengths 3, 7, 1, 5, 2, 6, 4.  Every ray is queued before
** the first load, and a ray finishes at the one point it hits, so the order
** in which rays finish is the order of the loads: the paper's rule (the
** fullest queue first) gives 7, 6, 5, 4, 3, 2, 1 rays per load. */
typedef struct order_state {
    const brt_ray *rays;
    size_t count, next, finished;
    uint32_t prims[28];
} order_state;

static size_t order_next(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    order_state *s = user;
    size_t n = 0;
    while (n < max && s->next < s->count) {
        rays[n] = s->rays[s->next];
        tags[n++] = s->next++;
    }
    return n;
}

static void order_finished(void *user, const brt_ray *ray, const brt_hit *hit,
                           const float normal[3], uint32_t visits, uint64_t tag)
{
    order_state *s = user;
    (void)ray;
    (void)normal;
    (void)visits;
    (void)tag;
    if (s->finished < 28) s->prims[s->finished] = hit->prim;
    s->finished++;
}

static void test_fullest_queue_first(void)
{
    static const uint32_t queued[7] = {3, 7, 1, 5, 2, 6, 4};
    tu_scene s = {0};
    brt_ray rays[28];
    order_state st;
    brt_scene *scene;
    uint32_t i, k, n = 0;
    int setting;
    for (i = 0; i < 7; i++) {
        const float x = 10.0f * (float)i;
        tu_add_triangle(&s, tu_add_vertex(&s, x, 0, 0), tu_add_vertex(&s, x + 1, 0, 0),
                        tu_add_vertex(&s, x, 1, 0));
        for (k = 0; k < queued[i]; k++, n++) {
            brt_ray r = {{0, 0.25f, 5}, {0, 0, -1}, 0.0f, INFINITY};
            r.org[0] = x + 0.1f + 0.1f * (float)k;
            rays[n] = r;
        }
    }
    scene = build_scene(&s, 1, 4, tu_scratch("order.brs"));
    for (setting = 0; scene && setting < 2 && !test_failed(); setting++) {
        brt_trace_options opt;
        brt_ray_source source;
        brt_error err;
        uint32_t want = 7;
        memset(&opt, 0, sizeof opt);
        opt.paper_scheduler = setting;   /* batchrt's scheduler and the paper's */
        memset(&st, 0, sizeof st);
        st.rays = rays;
        st.count = n;
        source.next_rays = order_next;
        source.finished = order_finished;
        source.user = &st;
        CHECK(brt_scene_trace_stream(scene, &opt, &source, NULL, &err) == BRT_OK, "%s", err.message);
        CHECK(st.finished == n, "%zu of %u rays finished", st.finished, (unsigned)n);
        /* runs of one prim, in the order loaded: 7 rays, then 6, ... */
        for (i = 0; i < n; want--) {
            const uint32_t prim = st.prims[i];
            for (k = 0; i < n && st.prims[i] == prim; i++) k++;
            CHECK(prim < 7 && k == queued[prim] && k == want,
                  "%s scheduler: load of prim %u served %u rays, expected the fullest queue (%u rays) next",
                  setting ? "the paper's" : "batchrt's", (unsigned)prim, (unsigned)k, (unsigned)want);
        }
    }
    brt_scene_close(scene);
    tu_scene_free(&s);
}

/* Rays with NaN, inf, zero directions and empty segments miss in both modes. */
static void test_degenerate_rays(void)
{
    fixture f;
    brt_scene *scene;
    uint64_t st = test_seed() + 9;
    size_t i;
    memset(&f, 0, sizeof f);
    tu_random_soup(&f.scene, &st, 300, 0.1f);
    CHECK(fixture_rays(&f, 50, st), "direct BVH build failed");
    for (i = 0; i < f.count; i += 5) {
        brt_ray *r = &f.rays[i];
        switch (i / 5 % 6) {
        case 0: r->org[1] = NAN; break;
        case 1: r->dir[0] = r->dir[1] = r->dir[2] = 0.0f; break;
        case 2: r->tnear = 2.0f; r->tfar = 1.0f; break;
        case 3: r->dir[2] = INFINITY; break;
        case 4: r->tfar = NAN; break;
        default: r->org[0] = -INFINITY; break;
        }
    }
    CHECK(fixture_direct(&f), "direct BVH build failed");
    for (i = 0; i < f.count; i += 5)
        EXPECT(f.direct[i].prim == BRT_NO_PRIM, "degenerate ray %zu hit in direct mode", i);
    scene = build_scene(&f.scene, 20, 16, tu_scratch("degenerate.brs"));
    if (scene) trace_matches(&f, scene, NULL, NULL, "degenerate rays");
    brt_scene_close(scene);
    fixture_free(&f);
}

/* ---- the scene file ------------------------------------------------------ */

static void write_obj(const tu_scene *s, const char *path)
{
    FILE *fp = fopen(path, "w");
    uint32_t i;
    if (!fp) return;
    for (i = 0; i < s->vcount; i++)
        fprintf(fp, "v %.9g %.9g %.9g\n", s->pos[3 * i], s->pos[3 * i + 1], s->pos[3 * i + 2]);
    for (i = 0; i < s->tcount; i++)
        fprintf(fp, "f %u %u %u\n", s->idx[3 * i] + 1, s->idx[3 * i + 1] + 1, s->idx[3 * i + 2] + 1);
    fclose(fp);
}

static int prepare(const char *mesh, const char *path, uint32_t point_tris, int *rebuilt,
                   brt_error *err)
{
    brt_scene_options opt;
    brt_scene *scene = NULL;
    brt_result r;
    memset(&opt, 0, sizeof opt);
    opt.point_tris = point_tris;
    opt.proxy_res = 16;
    r = brt_scene_prepare(mesh, path, &opt, &scene, rebuilt, err);
    brt_scene_close(scene);
    return r;
}

static void test_scene_reuse(void)
{
    tu_scene s;
    char mesh[512], path[512];
    brt_error err;
    int rebuilt = -1;
    uint64_t st = test_seed() + 3;
    memset(&s, 0, sizeof s);
    tu_random_soup(&s, &st, 200, 0.1f);
    snprintf(mesh, sizeof mesh, "%s/reuse.obj", test_tmpdir());
    snprintf(path, sizeof path, "%s/reuse.brs", test_tmpdir());
    write_obj(&s, mesh);
    CHECK(prepare(mesh, path, 20, &rebuilt, &err) == BRT_OK, "%s", err.message);
    EXPECT(rebuilt == 1, "a missing scene file was not built");
    CHECK(prepare(mesh, path, 20, &rebuilt, &err) == BRT_OK, "%s", err.message);
    EXPECT(rebuilt == 0, "an up-to-date scene file was rebuilt");
    CHECK(prepare(mesh, path, 30, &rebuilt, &err) == BRT_OK, "%s", err.message);
    EXPECT(rebuilt == 1, "a changed setting did not rebuild");
    tu_random_soup(&s, &st, 1, 0.1f);
    write_obj(&s, mesh);
    CHECK(prepare(mesh, path, 30, &rebuilt, &err) == BRT_OK, "%s", err.message);
    EXPECT(rebuilt == 1, "a changed mesh did not rebuild");
    tu_scene_free(&s);
}

/* Damages a copy of a good scene file at byte `at` (or truncates it to
** `at` bytes) and expects `words` in the error of open or trace. */
static void expect_damaged(const char *good, long at, int truncate_it, const char *words)
{
    char path[512], cmd[1200];
    brt_scene *scene = NULL;
    brt_error err;
    brt_result r;
    snprintf(path, sizeof path, "%s/damaged.brs", test_tmpdir());
    snprintf(cmd, sizeof cmd, "cp '%s' '%s'", good, path);
    if (system(cmd) != 0) {
        test_fail_at(__FILE__, __LINE__, "cannot copy %s", good);
        return;
    }
    if (truncate_it) {
        EXPECT(truncate(path, at) == 0, "truncate: %s", strerror(errno));
    } else {
        FILE *fp = fopen(path, "r+b");
        int c;
        if (!fp) return;
        fseek(fp, at, SEEK_SET);
        c = fgetc(fp);
        fseek(fp, at, SEEK_SET);
        fputc(c ^ 0x5A, fp);
        fclose(fp);
    }
    err.message[0] = 0;
    r = brt_scene_open(path, &scene, &err);
    if (r == BRT_OK) {
        /* The damage is in a blob: found when the blob is loaded. */
        brt_ray ray = {{0.5f, 0.5f, -1.0f}, {0.0f, 0.0f, 1.0f}, 0.0f, INFINITY};
        brt_hit hit;
        r = brt_scene_trace(scene, NULL, &ray, 1, &hit, NULL, &err);
        brt_scene_close(scene);
    }
    EXPECT(r == BRT_EFORMAT, "damage at %ld: result %s, expected a format error", at, brt_result_string(r));
    EXPECT(strstr(err.message, "damaged.brs") && strstr(err.message, words),
           "damage at %ld: message '%s' lacks '%s'", at, err.message, words);
}

/* A forged file: one u32 of good changed to value and every checksum
** repaired (as a forger would), so only the validators can refuse it. */
static void expect_forged(const char *good, size_t at, uint32_t value, const char *words)
{
    size_t size = 0;
    unsigned char *file = tu_slurp(good, &size);
    char path[512];
    brt_scene *scene = NULL;
    brt_error err;
    brt_result r;
    snprintf(path, sizeof path, "%s/forged.brs", test_tmpdir());   /* not scene_path's buffer: good may be it */
    CHECK(file && at + 4 <= size, "cannot read %s", good);
    memcpy(file + at, &value, 4);
    fuzz_repair_scene_checksums(file, size);
    CHECK(tu_spill(path, file, size), "cannot write %s", path);
    free(file);
    err.message[0] = 0;
    r = brt_scene_open(path, &scene, &err);
    brt_scene_close(scene);
    EXPECT(r == BRT_EFORMAT && strstr(err.message, words), "forged u32 at %zu: %s '%s', expected "
           "a format error about '%s'", at, brt_result_string(r), err.message, words);
}

/* The offset of section s (0 point table, 1 top level, 2 proxy pool) in
** a scene file (header layout in scene.c), or 0. */
static long section_offset(const char *path, int s)
{
    size_t size = 0;
    unsigned char *file = tu_slurp(path, &size);
    uint64_t offset = 0;
    if (file && size >= 256) memcpy(&offset, file + 56 + 24 * s, 8);
    free(file);
    return (long)offset;
}

/* The u32 at byte at of a file, or 0. */
static uint32_t file_u32(const char *path, size_t at)
{
    size_t size = 0;
    unsigned char *file = tu_slurp(path, &size);
    uint32_t value = 0;
    if (file && at + 4 <= size) memcpy(&value, file + at, 4);
    free(file);
    return value;
}

static void test_scene_errors(void)
{
    tu_scene s;
    brt_scene *scene;
    const char *good = tu_scratch("good.brs");
    brt_error err;
    uint64_t st = test_seed() + 4;
    struct stat info;
    memset(&s, 0, sizeof s);
    /* One big triangle across the unit square, so the probe ray loads it. */
    tu_add_triangle(&s, tu_add_vertex(&s, -1, -1, 0), tu_add_vertex(&s, 3, -1, 0), tu_add_vertex(&s, -1, 3, 0));
    tu_random_soup(&s, &st, 50, 0.1f);
    scene = build_scene(&s, 1000, 8, good);
    CHECK(scene, "build failed");
    brt_scene_close(scene);
    CHECK(stat(good, &info) == 0, "no scene file");
    expect_damaged(good, 0, 0, "magic");
    expect_damaged(good, 8, 0, "version");
    expect_damaged(good, 12, 0, "byte order");
    expect_damaged(good, 100, 0, "header checksum");
    expect_damaged(good, 4096 + 10, 0, "checksum");           /* inside the first blob */
    expect_damaged(good, (long)info.st_size - 4096 - 1, 1, "outside the file");
    expect_damaged(good, 100, 1, "truncated");
    /* In each section, damage only its checksum sees: the low byte of a
    ** box coordinate (point table, top level), the pool's magic. */
    CHECK(section_offset(good, 0) > 0, "no sections in %s", good);
    expect_damaged(good, section_offset(good, 0), 0, "point table checksum");
    expect_damaged(good, section_offset(good, 1), 0, "top-level BVH checksum");
    expect_damaged(good, section_offset(good, 2), 0, "proxy pool checksum");
    /* Checksums repaired: the first batch entry's proxy resolution (at
    ** 56), and its root (at 52) out of the pool. */
    expect_forged(good, (size_t)section_offset(good, 0) + 56, 3, "invalid proxy");
    expect_forged(good, (size_t)section_offset(good, 0) + 52, 0x7FFFFFF0u, "invalid proxy");
    /* The top-level root (children at 96) names its first child, here the
    ** one batching point, twice. */
    expect_forged(good, (size_t)section_offset(good, 1) + 100,
                  file_u32(good, (size_t)section_offset(good, 1) + 96), "bad leaf");
    EXPECT(brt_scene_open(tu_scratch("missing.brs"), &scene, &err) == BRT_EIO &&
           strstr(err.message, "missing.brs"), "missing file: '%s'", err.message);
    tu_scene_free(&s);
}

/* ---- read faults ----------------------------------------------------------- */

typedef struct fault_plan {
    long calls;
    long fail_at;              /* call number that fails with EIO; -1 never */
} fault_plan;

/* Every call returns at most 1000 bytes; every third fails with EINTR. */
static long faulty_read(int fd, void *buf, size_t size, uint64_t offset, void *user)
{
    fault_plan *plan = user;
    long call = plan->calls++;
    if (call == plan->fail_at) {
        errno = EIO;
        return -1;
    }
    if (call % 3 == 1) {
        errno = EINTR;
        return -1;
    }
    return (long)pread(fd, buf, size < 1000 ? size : 1000, (off_t)offset);
}

static void test_read_faults(void)
{
    fixture f;
    brt_scene *scene;
    brt_trace_options opt;
    fault_plan plan = {0, -1};
    brt_hit *hits;
    brt_error err;
    uint64_t st = test_seed() + 5;
    memset(&f, 0, sizeof f);
    tu_random_soup(&f.scene, &st, 1000, 0.05f);
    CHECK(fixture_rays(&f, 200, st), "direct BVH build failed");
    scene = build_scene(&f.scene, 100, 16, tu_scratch("faults.brs"));
    CHECK(scene, "build failed");
    memset(&opt, 0, sizeof opt);
    opt.read_fn = faulty_read;
    opt.read_user = &plan;
    opt.memory_limit = 32 << 10;
    opt.threads = 1;   /* the plan counts calls: no read-ahead */
    EXPECT(trace_matches(&f, scene, &opt, NULL, "short reads and EINTR"), "results changed");
    EXPECT(plan.calls > 10, "the injected reader was not used (%ld calls)", plan.calls);
    hits = malloc(f.count * sizeof *hits);
    plan.calls = 0;
    plan.fail_at = 25;
    EXPECT(brt_scene_trace(scene, &opt, f.rays, f.count, hits, NULL, &err) == BRT_EIO &&
           strstr(err.message, "faults.brs") && strstr(err.message, "read"),
           "EIO: '%s'", err.message);
    free(hits);
    brt_scene_close(scene);
    fixture_free(&f);
}

/* README, "A reader's path" 1: batching points are "top-down median splits
** ... at multiples of the batch size, so the points are full", and "none
** over the limit": for --point-tris N on M triangles (one bucket) that is
** ceil(M / N) points, every one holding N triangles but at most one (M mod
** N).  Read from the scene file's header and point table (README layout:
** the count at byte 32, a point's triangles at byte 48 of its 80), at N =
** M (one point), M - 1 (two: M - 1 and 1), and sizes between. */
static void test_points_are_full(void)
{
    static const uint32_t sizes[] = {300, 299, 1, 2, 7, 100, 150, 151, 1000};
    const uint32_t m = 300;
    tu_scene s;
    uint64_t st = test_seed() + 4411;
    size_t k;
    memset(&s, 0, sizeof s);
    tu_random_soup(&s, &st, m, 0.05f);
    for (k = 0; k < sizeof sizes / sizeof sizes[0]; k++) {
        const uint32_t n = sizes[k], want = (m + n - 1) / n;
        brt_scene *scene = tu_build_scene(&s, n, 8, 1, tu_scratch("full.brs"));
        unsigned char *f;
        size_t size;
        uint32_t j, points, partial = 0, total = 0;
        if (!scene) break;
        brt_scene_close(scene);
        f = tu_slurp(tu_scratch("full.brs"), &size);
        CHECK(f && size >= 256, "no scene file");
        points = brt_get_le32(f + 32);
        EXPECT(points == want, "--point-tris %u on %u triangles: %u batching points, want %u", (unsigned)n,
               (unsigned)m, (unsigned)points, (unsigned)want);
        for (j = 0; j < points && brt_get_le64(f + 56) + 80u * (j + 1) <= size; j++) {
            const uint32_t t = brt_get_le32(f + brt_get_le64(f + 56) + 80u * j + 48);
            total += t;
            EXPECT(t <= n, "--point-tris %u: point %u holds %u triangles", (unsigned)n, (unsigned)j, (unsigned)t);
            partial += t != n;
        }
        EXPECT(total == m && partial == (m % n != 0) && (m % n == 0 || partial == 1),
               "--point-tris %u: %u triangles in the points, %u not full (want %u)", (unsigned)n, (unsigned)total,
               (unsigned)partial, (unsigned)(m % n != 0));
        free(f);
    }
    tu_scene_free(&s);
}

void suite_batched(void)
{
    test_run("batched: == direct, soups, batch sizes 1..100000", test_soup_batch_sizes);
    test_run("batched: --point-tris N on M triangles makes ceil(M/N) full points", test_points_are_full);
    test_run("batched: == direct, proxy resolutions 2..256", test_soup_resolutions);
    test_run("batched: == direct, scales 1e-3 and 1e5", test_soup_scales);
    test_run("batched: == direct, flat batching-point boxes", test_flat_boxes);
    test_run("batched: exact proxies cull more, never a hit", test_exact_proxies);
    test_run("batched: an equal-t hit with a lower prim in a later batching point", test_equal_t_tie);
    test_run("batched: == direct, bunny_tiny", test_bunny_tiny);
    test_run("batched: == direct, bunny", test_bunny);
    test_run("batched: constant rays in flight", test_rays_in_flight);
    test_run("batched: fullest queue first", test_fullest_queue_first);
    test_run("batched: degenerate rays", test_degenerate_rays);
    test_run("batched: scene file reused, rebuilt when stale", test_scene_reuse);
    test_run("batched: corrupt, truncated, wrong-version scene files", test_scene_errors);
    test_run("batched: injected short reads, EINTR, EIO", test_read_faults);
}
