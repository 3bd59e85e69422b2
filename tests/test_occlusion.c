/*
** tests/test_occlusion.c -- occlusion queries (any hit within [tnear,
** tfar], Embree's rtcOccluded1) against two independent references:
**   - brute force: some triangle of the mesh passes brt_intersect_triangle
**     (the BVH's exact arithmetic) on the ray;
**   - the closest hit: a ray whose closest hit is at t is occluded with
**     tfar = t, and clear with tfar the float just below t (no triangle
**     is nearer, and a hit counts when t <= tfar).
** Then the batched traversal (brt_scene_occluded, and occlusion rays mixed
** with closest-hit rays in one stream) against the direct BVH byte for
** byte, over batch sizes, memory limits and proxies on and off; its
** statistics (occlusion_rays, occlusion_hits, the shadow-only loads); and
** the files of build/trace --occlusion (direct == batched) and
** build/hitdiff --occlusion.
*/
#include "test.h"
#include "util.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* ---- references ------------------------------------------------------- */

#define CUT_NONE 2   /* cut[i]: no closest-hit answer; else the answer, 1 or 0 */

/* Rays of every kind around the scene, and for each that hits, the same
** ray cut at its closest hit (cut 1) and just before it (cut 0). */
static brt_ray *make_rays(const tu_scene *s, const brt_bvh *bvh, size_t per_kind, uint64_t seed,
                          size_t *count, uint8_t **cut)
{
    float lo[3], hi[3];
    uint64_t st = seed;
    brt_ray *rays = malloc(3 * per_kind * TU_RAY_KINDS * sizeof *rays);
    size_t n = 0, i;
    *cut = malloc(3 * per_kind * TU_RAY_KINDS);
    int kind;
    tu_scene_bounds(s, lo, hi);
    for (kind = 0; kind < TU_RAY_KINDS; kind++)
        for (i = 0; i < per_kind; i++) {
            brt_hit hit;
            tu_make_ray(s, lo, hi, kind, &st, &rays[n]);
            brt_hit_clear(&hit);
            brt_bvh_intersect(bvh, &rays[n], &hit);
            (*cut)[n++] = CUT_NONE;
            if (hit.prim == BRT_NO_PRIM || !(hit.t > rays[n - 1].tnear)) continue;
            rays[n] = rays[n + 1] = rays[n - 1];
            rays[n].tfar = hit.t;
            rays[n + 1].tfar = nextafterf(hit.t, -INFINITY);
            (*cut)[n] = 1;
            (*cut)[n + 1] = 0;
            n += 2;
        }
    *count = n;
    return rays;
}

/* brt_bvh_occluded == brute force, and the closest-hit cuts answer 1, 0
** (a set of degenerate triangles, which never hit, has no cuts). */
static void check_direct(const tu_scene *s, size_t per_kind, int degenerate, const char *what)
{
    brt_bvh *bvh;
    brt_ray *rays;
    uint8_t *cut;
    size_t count, i, cuts = 0;
    CHECK(brt_bvh_build(s->pos, s->idx, s->tcount, NULL, &bvh) == BRT_OK, "%s: build failed", what);
    rays = make_rays(s, bvh, per_kind, test_seed(), &count, &cut);
    for (i = 0; i < count && !test_failed(); i++) {
        const brt_ray *r = &rays[i];
        int got = brt_bvh_occluded(bvh, r), want = tu_brute_occluded(s, r);
        EXPECT(got == want, "%s: ray %zu (o %a %a %a d %a %a %a, t %a..%a): BVH says %d, brute "
               "force %d", what, i, r->org[0], r->org[1], r->org[2], r->dir[0], r->dir[1],
               r->dir[2], r->tnear, r->tfar, got, want);
        if (cut[i] == CUT_NONE) continue;
        EXPECT(got == cut[i], "%s: ray %zu: occluded %d with tfar %s its closest hit t = %a", what,
               i, got, cut[i] ? "at" : "just below", cut[i] ? r->tfar : nextafterf(r->tfar, INFINITY));
        cuts++;
    }
    EXPECT(degenerate ? cuts == 0 : cuts > per_kind / 2, "%s: %zu cut rays (%s)", what, cuts,
           degenerate ? "a degenerate triangle was hit" : "the cut test is empty");
    free(rays);
    free(cut);
    brt_bvh_free(bvh);
}

/* ---- scenes ------------------------------------------------------------- */

/* Adversarial sets: a soup far from the origin, a tiny one, points and
** needles, coplanar overlapping triangles, the same triangles three times,
** unit squares on a lattice (axis rays through shared edges). */
static void adversarial(tu_scene *s, int which, uint64_t *st)
{
    uint32_t i;
    memset(s, 0, sizeof *s);
    if (which == 0) tu_random_soup(s, st, 1500, 0.05f);
    if (which == 1) {
        tu_random_soup(s, st, 1500, 0.02f);
        tu_scene_transform(s, 1e5f, 3e9f);
    }
    if (which == 2) {
        tu_random_soup(s, st, 1500, 0.3f);
        tu_scene_transform(s, 1e-3f, 0.0f);
    }
    if (which == 3)
        for (i = 0; i < 1500; i++) {
            float x = tu_rnd(st, 0, 1), y = tu_rnd(st, 0, 1), z = tu_rnd(st, 0, 1);
            float dx = i % 3 == 0 ? 0.0f : 0.01f;
            uint32_t a = tu_add_vertex(s, x, y, z), b = tu_add_vertex(s, x + dx, y, z);
            tu_add_triangle(s, a, b, i % 5 == 0 ? a : tu_add_vertex(s, x + 2 * dx, y, z));
        }
    if (which == 4)
        for (i = 0; i < 1500; i++) {
            float x = tu_rnd(st, 0, 1), y = tu_rnd(st, 0, 1);
            tu_add_triangle(s, tu_add_vertex(s, x, y, 0.5f), tu_add_vertex(s, x + 0.1f, y, 0.5f),
                            tu_add_vertex(s, x, y + 0.1f, 0.5f));
        }
    if (which == 5) {
        uint32_t n;
        tu_random_soup(s, st, 500, 0.1f);
        n = s->tcount;
        for (i = 0; i < 2 * n; i++)
            tu_add_triangle(s, s->idx[3 * (i % n)], s->idx[3 * (i % n) + 1], s->idx[3 * (i % n) + 2]);
    }
    if (which == 6) {
        int x, y;
        for (x = 0; x < 20; x++)
            for (y = 0; y < 20; y++) {
                uint32_t a = tu_add_vertex(s, (float)x, (float)y, 0), b = tu_add_vertex(s, x + 1.0f, (float)y, 0);
                uint32_t c = tu_add_vertex(s, x + 1.0f, y + 1.0f, 0), d = tu_add_vertex(s, (float)x, y + 1.0f, 0);
                tu_add_triangle(s, a, b, c);
                tu_add_triangle(s, a, c, d);
            }
    }
}

#define ADVERSARIAL_SETS 7
static const char *const set_name[ADVERSARIAL_SETS] = {
    "soup", "soup at 3e9", "tiny soup", "points and needles", "coplanar", "triplicates", "lattice"};

static void test_adversarial_brute_force(void)
{
    uint64_t st = test_seed() ^ 0x0CC1;
    int which;
    for (which = 0; which < ADVERSARIAL_SETS && !test_failed(); which++) {
        tu_scene s;
        adversarial(&s, which, &st);
        check_direct(&s, 150, which == 3, set_name[which]);
        tu_scene_free(&s);
    }
}

static void test_shared_meshes_brute_force(void)
{
    static const char *const names[] = {"bunny_tiny.obj", "bunny.obj.gz"};
    size_t i;
    for (i = 0; i < 2 && !test_failed(); i++) {
        const char *path = test_shared_mesh(names[i]);
        brt_mesh mesh;
        brt_error err;
        tu_scene s;
        if (!path) { test_skip("%s: ../shared not found", names[i]); return; }
        CHECK(brt_mesh_load(path, &mesh, &err) == BRT_OK, "%s: %s", names[i], err.message);
        memset(&s, 0, sizeof s);
        s.pos = mesh.positions;
        s.idx = mesh.indices;
        s.vcount = mesh.vertex_count;
        s.tcount = mesh.triangle_count;
        check_direct(&s, i == 0 ? 200 : 25, 0, names[i]);
        brt_mesh_free(&mesh);
    }
}

/* ---- batched == direct ---------------------------------------------------- */

static brt_scene *build_scene(const tu_scene *s, uint32_t point_tris, const char *name)
{
    return tu_build_scene(s, point_tris, 32, 0, tu_scratch(name));
}

/* brt_scene_occluded == brt_bvh_occluded for every ray, over memory limits
** (none, half the geometry, one byte), proxies off and on, and the paper's
** scheduler (every ray queued, proxies always consulted). */
static void sweep(const tu_scene *s, const brt_ray *rays, const uint8_t *want, size_t count,
                  uint32_t point_tris, const char *what)
{
    brt_scene *scene = build_scene(s, point_tris, "occlusion.brs");
    uint8_t *got = malloc(count ? count : 1);
    uint64_t limits[3] = {0, 0, 1}, occluded = 0;
    size_t i;
    int l, setting;
    for (i = 0; i < count; i++) occluded += want[i];
    for (l = 0; scene && l < 3 && !test_failed(); l++)
        for (setting = 0; setting < 4 && !test_failed(); setting++) {
            brt_trace_options opt;
            brt_stats stats;
            brt_error err;
            memset(&opt, 0, sizeof opt);
            opt.memory_limit = limits[l];
            opt.no_proxy = setting & 1;
            opt.paper_scheduler = setting >> 1;
            memset(got, 0xAA, count);
            CHECK(brt_scene_occluded(scene, &opt, rays, count, got, &stats, &err) == BRT_OK,
                  "%s: %s", what, err.message);
            if (l == 0) limits[1] = stats.geometry_bytes / 2 + 1;
            for (i = 0; i < count && !test_failed(); i++)
                EXPECT(got[i] == want[i], "%s, batch %u, limit %llu, setting %d: ray %zu: batched "
                       "%u, direct %u", what, point_tris, (unsigned long long)limits[l], setting, i,
                       got[i], want[i]);
            EXPECT(stats.rays == count && stats.occlusion_rays == count &&
                   stats.occlusion_hits == occluded,
                   "%s: statistics say %llu rays, %llu shadow rays, %llu occluded; expected %zu, "
                   "%zu, %llu", what, (unsigned long long)stats.rays,
                   (unsigned long long)stats.occlusion_rays, (unsigned long long)stats.occlusion_hits,
                   count, count, (unsigned long long)occluded);
            /* Only occlusion rays: every load is theirs. */
            EXPECT(stats.occlusion_batch_loads == stats.batch_loads &&
                   stats.occlusion_disk_bytes_read == stats.disk_bytes_read,
                   "%s: %llu of %llu loads booked to the shadow rays", what,
                   (unsigned long long)stats.occlusion_batch_loads,
                   (unsigned long long)stats.batch_loads);
        }
    free(got);
    brt_scene_close(scene);
}

static void test_batched_equals_direct(void)
{
    static const uint32_t batch[] = {1, 40, 400};
    uint64_t st = test_seed() ^ 0x0CC2;
    int which;
    for (which = 0; which < ADVERSARIAL_SETS && !test_failed(); which += 2) {
        tu_scene s;
        brt_bvh *bvh;
        brt_ray *rays;
        uint8_t *want, *cut;
        size_t count, i, b;
        adversarial(&s, which, &st);
        CHECK(brt_bvh_build(s.pos, s.idx, s.tcount, NULL, &bvh) == BRT_OK, "build failed");
        rays = make_rays(&s, bvh, 60, test_seed() + (uint64_t)which, &count, &cut);
        free(cut);
        want = malloc(count);
        for (i = 0; i < count; i++) want[i] = (uint8_t)brt_bvh_occluded(bvh, &rays[i]);
        for (b = 0; b < sizeof batch / sizeof *batch && !test_failed(); b++)
            sweep(&s, rays, want, count, batch[b], set_name[which]);
        free(want);
        free(rays);
        brt_bvh_free(bvh);
        tu_scene_free(&s);
    }
}

/* ---- both kinds in one stream ----------------------------------------- */

/* Ray i of the fixture goes out twice: as a closest-hit ray (tag 2i) and
** as an occlusion ray (tag 2i+1 | BRT_TAG_OCCLUSION), one at a time so that
** queues mix both kinds. */
typedef struct mixed {
    const brt_ray *rays;
    size_t count, next;
    brt_hit *hits;
    uint8_t *occluded;
    int bad_record;
} mixed;

static size_t mixed_next(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    mixed *m = user;
    size_t n = 0;
    while (n < max && m->next < 2 * m->count) {
        rays[n] = m->rays[m->next / 2];
        tags[n++] = m->next % 2 ? m->next | BRT_TAG_OCCLUSION : m->next;
        m->next++;
    }
    return n;
}

static void mixed_finished(void *user, const brt_ray *ray, const brt_hit *hit,
                           const float normal[3], uint32_t visits, uint64_t tag)
{
    mixed *m = user;
    uint64_t k = tag & ~BRT_TAG_OCCLUSION;
    (void)ray;
    (void)visits;
    if (!(tag & BRT_TAG_OCCLUSION) != !(k % 2)) m->bad_record = 1;   /* the kind bit came back */
    if (tag & BRT_TAG_OCCLUSION) {
        m->occluded[k / 2] = hit->prim != BRT_NO_PRIM;
        /* the documented record: miss, or t = 0, prim = 0, u = v = 0; no normal */
        if ((hit->prim != BRT_NO_PRIM && (hit->t != 0 || hit->prim != 0 || hit->u != 0 || hit->v != 0))
            || normal[0] != 0 || normal[1] != 0 || normal[2] != 0)
            m->bad_record = 1;
    } else {
        m->hits[k / 2] = *hit;
    }
}

static void test_mixed_stream(void)
{
    uint64_t st = test_seed() ^ 0x0CC3;
    tu_scene s;
    brt_bvh *bvh;
    brt_ray *rays;
    brt_scene *scene;
    uint8_t *cut;
    size_t count, i;
    int setting;
    adversarial(&s, 0, &st);
    CHECK(brt_bvh_build(s.pos, s.idx, s.tcount, NULL, &bvh) == BRT_OK, "build failed");
    rays = make_rays(&s, bvh, 100, test_seed(), &count, &cut);
    free(cut);
    scene = build_scene(&s, 60, "mixed.brs");
    for (setting = 0; scene && setting < 3 && !test_failed(); setting++) {
        brt_ray_source source;
        brt_trace_options opt;
        brt_stats stats;
        brt_error err;
        mixed m;
        uint64_t occluded = 0;
        memset(&m, 0, sizeof m);
        m.rays = rays;
        m.count = count;
        m.hits = malloc(count * sizeof *m.hits);
        m.occluded = malloc(count);
        source.next_rays = mixed_next;
        source.finished = mixed_finished;
        source.user = &m;
        memset(&opt, 0, sizeof opt);
        opt.memory_limit = setting == 0 ? 0 : 1;
        opt.no_proxy = setting == 2;
        opt.rays_in_flight = 50;
        CHECK(brt_scene_trace_stream(scene, &opt, &source, &stats, &err) == BRT_OK, "%s",
              err.message);
        for (i = 0; i < count && !test_failed(); i++) {
            brt_hit want;
            int occ = brt_bvh_occluded(bvh, &rays[i]);
            brt_hit_clear(&want);
            brt_bvh_intersect(bvh, &rays[i], &want);
            EXPECT(memcmp(&want, &m.hits[i], sizeof want) == 0 && m.occluded[i] == occ,
                   "setting %d, ray %zu: closest hit prim %u (direct %u), occluded %u (direct %d)",
                   setting, i, (unsigned)m.hits[i].prim, (unsigned)want.prim, m.occluded[i], occ);
            occluded += (uint64_t)occ;
        }
        EXPECT(!m.bad_record, "setting %d: an occlusion record or tag not as documented", setting);
        EXPECT(stats.rays == 2 * count && stats.occlusion_rays == count &&
               stats.occlusion_hits == occluded,
               "setting %d: %llu rays, %llu shadow rays, %llu occluded; expected %zu, %zu, %llu",
               setting, (unsigned long long)stats.rays, (unsigned long long)stats.occlusion_rays,
               (unsigned long long)stats.occlusion_hits, 2 * count, count,
               (unsigned long long)occluded);
        EXPECT(stats.occlusion_batch_loads <= stats.batch_loads &&
               stats.occlusion_disk_bytes_read <= stats.disk_bytes_read,
               "setting %d: more shadow loads than loads", setting);
        free(m.hits);
        free(m.occluded);
    }
    brt_scene_close(scene);
    free(rays);
    brt_bvh_free(bvh);
    tu_scene_free(&s);
}

/* ---- the programs ------------------------------------------------------ */

static void test_trace_and_hitdiff(void)
{
    static const char *const batched[] = {
        "--batched --point-tris 30 --scene @/t.brs",
        "--batched --point-tris 30 --scene @/t.brs --memory 1K",
        "--batched --point-tris 30 --scene @/t.brs --memory 1K --no-proxy"};
    unsigned char *direct, *other;
    char *out;
    size_t n_direct = 0, n_other = 0, n_rays = 0, i;
    int ones = 0;
    CHECK(tu_run("mkscene crown @/occ.obj --scale 0.01") == 0, "mkscene failed");
    CHECK(tu_run("raygen @/occ.obj @/occ.rays --kind random --count 3000 --seed 5") == 0,
          "raygen failed");
    CHECK(tu_run("trace @/occ.obj @/occ.rays @/direct.occ --occlusion --stats @/occ.json") == 0,
          "trace --occlusion failed");
    direct = tu_slurp(tu_scratch("direct.occ"), &n_direct);
    free(tu_slurp(tu_scratch("occ.rays"), &n_rays));
    CHECK(direct && n_direct == n_rays / BRT_RAY_BYTES && n_direct == 3000,
          "the occlusion file holds %zu bytes for %zu rays", n_direct, n_rays / BRT_RAY_BYTES);
    for (i = 0; i < n_direct; i++) {
        EXPECT(direct[i] <= 1, "byte %zu is %u", i, direct[i]);
        ones += direct[i];
    }
    EXPECT(ones > 0 && ones < 3000, "%d of 3000 rays occluded: the test says nothing", ones);
    for (i = 0; i < sizeof batched / sizeof *batched && !test_failed(); i++) {
        CHECK(tu_run("trace @/occ.obj @/occ.rays @/batched.occ --occlusion %s", batched[i]) == 0,
              "trace --occlusion %s failed", batched[i]);
        other = tu_slurp(tu_scratch("batched.occ"), &n_other);
        EXPECT(other && n_other == n_direct && memcmp(other, direct, n_direct) == 0,
               "trace --occlusion %s: not the bytes of --direct", batched[i]);
        free(other);
    }
    CHECK(tu_run("hitdiff @/direct.occ @/batched.occ --occlusion") == 0,
          "hitdiff --occlusion: identical files disagree");
    direct[7] ^= 1;
    CHECK(tu_spill(tu_scratch("flipped.occ"), direct, n_direct), "cannot write");
    EXPECT(tu_run("hitdiff @/direct.occ @/flipped.occ --occlusion") == 1,
           "hitdiff --occlusion: one flipped byte is not a disagreement");
    out = tu_last_stdout();
    EXPECT(out && strstr(out, "1 of 3000 rays disagree") != NULL,
           "hitdiff --occlusion: the summary does not count the flipped byte");
    free(out);
    EXPECT(tu_run("hitdiff @/direct.occ @/occ.rays --occlusion") == 1,
           "hitdiff --occlusion took a ray file for an occlusion file");
    out = tu_last_stderr();
    EXPECT(out && strstr(out, "not an occlusion file") != NULL,
           "hitdiff --occlusion: no message for a ray file");
    free(out);
    free(direct);
}

/* The walk stops at the first occluder.  Two triangles, one per batching
** point, both through o = (0.1, 0.1, 0): A in z = 0, B in x + z = 0.1.  A
** ray from o down -z with tnear = 0 hits both at t = 0, and both points are
** entered at t = 0.  As a closest-hit ray it is queued at both (a point
** entered exactly at the closest hit is visited); as an occlusion ray it
** is done at the first, its queued visits 1.  (A walk that went on would
** queue it at the second, entered at 0 <= its limit 0.) */
static void test_walk_stops_at_occluder(void)
{
    static float positions[] = {-1, -1, 0, 1, -1, 0, 0, 1, 0,
                                1.1f, -1, -1, -0.9f, -1, 1, 0.1f, 2, 0};
    static uint32_t indices[] = {0, 1, 2, 3, 4, 5};
    brt_mesh mesh = {positions, indices, 6, 2};
    brt_ray ray = {{0.1f, 0.1f, 0.0f}, {0.0f, 0.0f, -1.0f}, 0.0f, INFINITY};
    brt_scene_options sopt;
    brt_scene *scene = NULL;
    brt_stats closest, occlusion;
    brt_hit hit;
    uint8_t occluded = 0;
    brt_error err;
    memset(&sopt, 0, sizeof sopt);
    sopt.point_tris = 1;
    sopt.proxy_res = 4;
    CHECK(brt_scene_build(&mesh, &sopt, 0, tu_scratch("stop.brs"), &err) == BRT_OK, "%s", err.message);
    CHECK(brt_scene_open(tu_scratch("stop.brs"), &scene, &err) == BRT_OK, "%s", err.message);
    EXPECT(brt_scene_trace(scene, NULL, &ray, 1, &hit, &closest, &err) == BRT_OK && hit.t == 0.0f,
           "closest hit: t = %g, %s", hit.t, err.message);
    EXPECT(brt_scene_occluded(scene, NULL, &ray, 1, &occluded, &occlusion, &err) == BRT_OK && occluded,
           "not occluded: %s", err.message);
    EXPECT(closest.queued_visits == 2 && occlusion.queued_visits == 1,
           "queued visits: closest-hit ray %llu (expected 2), occlusion ray %llu (expected 1)",
           (unsigned long long)closest.queued_visits, (unsigned long long)occlusion.queued_visits);
    brt_scene_close(scene);
}

void suite_occlusion(void)
{
    test_run("occlusion: BVH == brute force and the closest-hit cuts, adversarial sets",
             test_adversarial_brute_force);
    test_run("occlusion: BVH == brute force, shared meshes", test_shared_meshes_brute_force);
    test_run("occlusion: batched == direct over batch sizes, limits, proxies",
             test_batched_equals_direct);
    test_run("occlusion: both kinds in one stream", test_mixed_stream);
    test_run("occlusion: trace --occlusion direct == batched, hitdiff --occlusion",
             test_trace_and_hitdiff);
    test_run("occlusion: the walk stops at the first occluder", test_walk_stops_at_occluder);
}
