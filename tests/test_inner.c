/*
** tests/test_inner.c -- inner proxies (svdag.c, "Inner proxies"): voxels
** that settle an occlusion ray with tfar = +inf as occluded without a
** load.  One-sided, ray by ray: an inner proxy may under-report, but it
** must never say occluded where the exact query (brute force over every
** triangle with brt_intersect_triangle) says clear.  Dense random rays,
** origins inside the solids among them, on closed solids and on solids
** that are almost closed (one triangle removed, a hole smaller than a
** voxel), nested shells, touching and overlapping solids, and solids cut
** by batching-point boundaries.  And the mechanism is on: closed solids
** get inner voxels that stop rays (occlusion_inner_stopped), open ones none.
*/
#include "test.h"
#include "util.h"
#include "../examples/lib/scenes.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* ---- solids ----------------------------------------------------------- */

/* A cube's surface, n x n quads a face, its lattice points pushed onto a
** bumpy sphere of radius r around c (jitter: relative bumps).  Vertices are
** shared by lattice point, so the surface is closed; flip reverses the
** orientation (parity does not care). */
static void add_ball(tu_scene *s, const float c[3], float r, uint32_t n, float jitter,
                     uint64_t *st)
{
    uint32_t m = n + 1, *id = malloc((size_t)m * m * m * sizeof *id), i, j, k, f;
    for (k = 0; k < m * m * m; k++) id[k] = 0xFFFFFFFFu;
    for (k = 0; k <= n; k++)
        for (j = 0; j <= n; j++)
            for (i = 0; i <= n; i++) {
                double p[3], l;
                int a;
                if (i != 0 && i != n && j != 0 && j != n && k != 0 && k != n) continue;
                p[0] = 2.0 * i / n - 1; p[1] = 2.0 * j / n - 1; p[2] = 2.0 * k / n - 1;
                l = sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
                l = r * (1 + jitter * tu_rnd(st, -1, 1)) / l;
                for (a = 0; a < 3; a++) p[a] = c[a] + p[a] * l;
                id[i + m * (j + m * k)] = tu_add_vertex(s, (float)p[0], (float)p[1], (float)p[2]);
            }
    /* Each face: axis f fixed at 0 or n; quads (u, v) split in two. */
    for (f = 0; f < 6; f++) {
        uint32_t ax = f >> 1, au = (ax + 1) % 3, av = (ax + 2) % 3, side = f & 1 ? n : 0, u, v;
        for (v = 0; v < n; v++)
            for (u = 0; u < n; u++) {
                uint32_t q[4], corner;
                for (corner = 0; corner < 4; corner++) {
                    uint32_t at[3];
                    at[ax] = side;
                    at[au] = u + (corner == 1 || corner == 2);
                    at[av] = v + (corner >= 2);
                    q[corner] = id[at[0] + m * (at[1] + m * at[2])];
                }
                if (f & 1) {
                    tu_add_triangle(s, q[0], q[1], q[2]);
                    tu_add_triangle(s, q[0], q[2], q[3]);
                } else {
                    tu_add_triangle(s, q[0], q[2], q[1]);
                    tu_add_triangle(s, q[0], q[3], q[2]);
                }
            }
    }
    free(id);
}

/* Removes triangle t (the last one takes its place). */
static void remove_triangle(tu_scene *s, uint32_t t)
{
    memcpy(s->idx + 3 * (size_t)t, s->idx + 3 * (size_t)(s->tcount - 1), 3 * sizeof *s->idx);
    s->tcount--;
}

enum { SOLID_ONE, SOLID_HOLE, SOLID_SMALL_HOLE, SOLID_NESTED, SOLID_TOUCHING, SOLID_OVERLAPPING,
       SOLID_MANY, SOLID_PEBBLES, SOLID_KINDS };
static const char *const solid_name[SOLID_KINDS] = {
    "closed ball", "one triangle removed", "hole smaller than a voxel", "nested shells",
    "touching balls", "overlapping balls", "twelve balls and an open sheet",
    "a hollow shell of separate cubes, gaps under a voxel"};

static void make_solids(tu_scene *s, int kind, uint64_t *st)
{
    float c[3] = {0.5f, 0.5f, 0.5f}, d[3];
    int i;
    memset(s, 0, sizeof *s);
    switch (kind) {
    case SOLID_ONE: add_ball(s, c, 0.4f, 8, 0.05f, st); break;
    case SOLID_HOLE:
        add_ball(s, c, 0.4f, 8, 0.05f, st);
        remove_triangle(s, (uint32_t)(brt_random_u64(st) % s->tcount));
        break;
    case SOLID_SMALL_HOLE:   /* 48 quads a side: triangles well under a voxel of 16^3 */
        add_ball(s, c, 0.4f, 48, 0.0f, st);
        remove_triangle(s, (uint32_t)(brt_random_u64(st) % s->tcount));
        break;
    case SOLID_NESTED:
        add_ball(s, c, 0.45f, 8, 0.02f, st);
        add_ball(s, c, 0.25f, 6, 0.02f, st);
        break;
    case SOLID_TOUCHING:     /* two unit cubes sharing a face: one welded component */
        c[0] = 0.25f;
        add_ball(s, c, 0.25f * 1.7320508f, 1, 0.0f, st);
        c[0] = 0.75f;
        add_ball(s, c, 0.25f * 1.7320508f, 1, 0.0f, st);
        break;
    case SOLID_OVERLAPPING:  /* the overlap has parity 2: outside for the count */
        c[0] = 0.35f;
        add_ball(s, c, 0.3f, 8, 0.03f, st);
        c[0] = 0.65f;
        add_ball(s, c, 0.3f, 8, 0.03f, st);
        break;
    case SOLID_PEBBLES:      /* walls all round the middle, yet rays escape between cubes */
        for (i = 0; i < 512; i++) {
            int x = i & 7, y = i >> 3 & 7, z = i >> 6;
            if (x != 0 && x != 7 && y != 0 && y != 7 && z != 0 && z != 7) continue;
            d[0] = 0.0625f + 0.125f * (float)x;
            d[1] = 0.0625f + 0.125f * (float)y;
            d[2] = 0.0625f + 0.125f * (float)z;
            add_ball(s, d, 0.05f * 1.7320508f, 1, 0.0f, st);
        }
        break;
    default:
        for (i = 0; i < 12; i++) {
            d[0] = tu_rnd(st, 0.1f, 0.9f);
            d[1] = tu_rnd(st, 0.1f, 0.9f);
            d[2] = tu_rnd(st, 0.1f, 0.9f);
            add_ball(s, d, tu_rnd(st, 0.03f, 0.12f), 4, 0.1f, st);
        }
        {   /* an open sheet through the middle: walls nothing in */
            uint32_t a = tu_add_vertex(s, 0, 0, 0.5f), b = tu_add_vertex(s, 1, 0, 0.52f);
            uint32_t e = tu_add_vertex(s, 1, 1, 0.5f), f = tu_add_vertex(s, 0, 1, 0.48f);
            tu_add_triangle(s, a, b, e);
            tu_add_triangle(s, a, e, f);
        }
    }
}

/* ---- rays and the reference -------------------------------------------- */

/* Shadow-like rays: origins anywhere in the box around the solids (many
** inside them), on the surfaces, or at their vertices; tnear 0, small or
** past the solid's middle; tfar +inf but for one ray in eight. */
static void make_ray(const tu_scene *s, uint64_t *st, brt_ray *r)
{
    uint32_t kind = (uint32_t)(brt_random_u64(st) % 4), t = (uint32_t)(brt_random_u64(st) % s->tcount);
    float a = tu_rnd(st, 0, 1), b = tu_rnd(st, 0, 1);
    int i;
    if (a + b > 1) { a = 1 - a; b = 1 - b; }
    for (i = 0; i < 3; i++) {
        const float *v0 = tu_vertex(s, t, 0), *v1 = tu_vertex(s, t, 1), *v2 = tu_vertex(s, t, 2);
        r->org[i] = kind == 0 ? tu_rnd(st, -0.1f, 1.1f) : kind == 1 ? tu_rnd(st, 0.2f, 0.8f)
                  : kind == 2 ? (1 - a - b) * v0[i] + a * v1[i] + b * v2[i] : v0[i];
    }
    tu_random_unit(st, r->dir);
    if (brt_random_u64(st) % 2) for (i = 0; i < 3; i++) r->dir[i] *= 3.0f;   /* not normalised */
    i = (int)(brt_random_u64(st) % 4);
    r->tnear = i == 0 ? 0.0f : i == 1 ? 1e-4f : tu_rnd(st, 0, 0.6f);
    r->tfar = brt_random_u64(st) % 8 ? INFINITY : tu_rnd(st, 0, 1);
}

/* The closed components of an indexed mesh, over its corners copied out
** into *corners (free it after brt_solids_free). */
static brt_result solids_of(const float *pos, const uint32_t *idx, uint32_t n, brt_solids **out,
                           float **corners)
{
    uint32_t t;
    int k;
    *out = NULL;
    *corners = malloc((9 * (size_t)n + 1) * sizeof **corners);
    if (!*corners) return BRT_ENOMEM;
    for (t = 0; t < n; t++)
        for (k = 0; k < 3; k++) memcpy(*corners + 9 * (size_t)t + 3 * k, pos + 3 * (size_t)idx[3 * t + k], 12);
    return brt_solids_build(*corners, 9, n, out);
}

/* The inner proxy of a whole soup at resolution res, through the API, in
** a grid over the box [lo, hi] (NULL: the soup's box). */
static brt_result inner_in(const tu_scene *s, uint32_t res, const float *lo_in, const float *hi_in,
                           brt_svdag *dag, brt_proxy *p, uint64_t *voxels, uint32_t *closed)
{
    float lo[3], hi[3];
    brt_solids *solids = NULL;
    float *corners = NULL;
    brt_grid g;
    brt_result r;
    tu_scene_bounds(s, lo, hi);
    r = brt_grid_init(&g, lo_in ? lo_in : lo, hi_in ? hi_in : hi, res);
    if (r == BRT_OK) r = solids_of(s->pos, s->idx, s->tcount, &solids, &corners);
    if (r == BRT_OK) {
        *closed = brt_solids_triangles(solids);
        r = brt_voxelize_inner(&g, solids);
    }
    if (r == BRT_OK) {
        *voxels = brt_grid_count(&g);
        r = brt_svdag_add(dag, &g, p);
    }
    brt_solids_free(solids);
    free(corners);
    brt_grid_free(&g);
    return r;
}

static brt_result inner_of(const tu_scene *s, uint32_t res, brt_svdag *dag, brt_proxy *p,
                           uint64_t *voxels, uint32_t *closed)
{
    return inner_in(s, res, NULL, NULL, dag, p, voxels, closed);
}

/* ---- tests ------------------------------------------------------------- */

/* Every solid, at two resolutions: brt_inner_occludes never says occluded
** where brute force says clear; closed solids have inner voxels that stop
** many rays, open ones have none. */
static void test_one_sided_api(void)
{
    static const uint32_t resolutions[] = {16, 32, 32};
    static const float part_lo[3] = {0.3f, 0.25f, 0.35f}, part_hi[3] = {0.62f, 0.7f, 0.55f};
    int kind;
    size_t q;
    for (kind = 0; kind < SOLID_KINDS && !test_failed(); kind++)
        for (q = 0; q < 3 && !test_failed(); q++) {
            uint64_t st = test_seed() + 977u * (uint64_t)kind, voxels = 0;
            uint32_t closed = 0, i, stopped = 0, occluded = 0, inside_voxels_expected;
            brt_svdag *dag = NULL;
            brt_proxy p;
            tu_scene s;
            make_solids(&s, kind, &st);
            CHECK(brt_svdag_create(&dag) == BRT_OK, "no pool");
            /* the third grid covers part of the solids only: a batching
            ** point that cuts them */
            CHECK(inner_in(&s, resolutions[q], q == 2 ? part_lo : NULL, q == 2 ? part_hi : NULL,
                           dag, &p, &voxels, &closed) == BRT_OK,
                  "%s: inner voxelization failed", solid_name[kind]);
            inside_voxels_expected = kind != SOLID_HOLE && kind != SOLID_SMALL_HOLE &&
                                     kind != SOLID_PEBBLES;
            EXPECT(kind == SOLID_PEBBLES || (q == 2 && kind == SOLID_MANY) ||
                       (inside_voxels_expected ? voxels > 0 : voxels == 0),
                   "%s, res %u: %llu inner voxels", solid_name[kind], resolutions[q],
                   (unsigned long long)voxels);
            EXPECT(kind == SOLID_HOLE || kind == SOLID_SMALL_HOLE
                       ? closed == 0 : closed + 2 * (kind == SOLID_MANY) == s.tcount,
                   "%s: %u of %u triangles in closed components", solid_name[kind], closed, s.tcount);
            for (i = 0; i < 8000 && i < 12000000u / s.tcount && !test_failed(); i++) {
                brt_ray r;
                int says;
                make_ray(&s, &st, &r);
                says = brt_inner_occludes(dag, &p, &r);
                occluded += tu_brute_occluded(&s, &r);
                stopped += (uint32_t)says;
                if (says && !tu_brute_occluded(&s, &r))
                    test_fail_at(__FILE__, __LINE__, "%s, res %u, seed %llu, ray %u: inner proxy says "
                                 "occluded, brute force says clear: org %a %a %a dir %a %a %a tnear %a",
                                 solid_name[kind], resolutions[q], (unsigned long long)test_seed(), i,
                                 r.org[0], r.org[1], r.org[2], r.dir[0], r.dir[1], r.dir[2], r.tnear);
            }
            EXPECT(!inside_voxels_expected || q != 1 || stopped > occluded / 20,
                   "%s, res %u: inner proxy stopped %u of %u occluded rays", solid_name[kind],
                   resolutions[q], stopped, occluded);
            brt_svdag_free(dag);
            tu_scene_free(&s);
        }
}

/* Where [lo, hi] (world) meets the ray at t >= tnear, in double: the
** parameter interval, empty when t0 > t1. */
static void box_interval(const brt_ray *r, const double lo[3], const double hi[3], double *t0,
                         double *t1)
{
    int a;
    *t0 = r->tnear;
    *t1 = INFINITY;
    for (a = 0; a < 3; a++) {
        double u = (lo[a] - r->org[a]) / r->dir[a], v = (hi[a] - r->org[a]) / r->dir[a];
        if (r->dir[a] == 0) {
            if (r->org[a] <= lo[a] || r->org[a] >= hi[a]) *t1 = -INFINITY;
            continue;
        }
        if (u > v) { double w = u; u = v; v = w; }
        if (u > *t0) *t0 = u;
        if (v < *t1) *t1 = v;
    }
}

/* The margin, white box: with one voxel set, the cast says occluded only
** for rays that pass through the voxel's core (a quarter voxel in from its
** faces) at t >= tnear, and does say it for rays well through the core. */
static void test_core_margin(void)
{
    float lo[3] = {0, 0, 0}, hi[3] = {4, 4, 4};
    uint64_t st = test_seed();
    uint32_t i, yes = 0, core_rays = 0;
    brt_svdag *dag = NULL;
    brt_proxy p;
    brt_grid g;
    CHECK(brt_grid_init(&g, lo, hi, 4) == BRT_OK && brt_svdag_create(&dag) == BRT_OK, "no grid");
    brt_grid_set(&g, 1, 2, 1);
    CHECK(brt_svdag_add(dag, &g, &p) == BRT_OK, "no proxy");
    brt_grid_free(&g);
    for (i = 0; i < 200000 && !test_failed(); i++) {
        double in_lo[3], in_hi[3], out_lo[3], out_hi[3], t0, t1, u0, u1;
        static const uint32_t at[3] = {1, 2, 1};
        brt_ray r;
        int a, says;
        for (a = 0; a < 3; a++) {
            r.org[a] = tu_rnd(&st, -1, 5);
            out_lo[a] = p.origin[a] + (at[a] + 0.24) * (double)p.cell;
            out_hi[a] = p.origin[a] + (at[a] + 0.76) * (double)p.cell;
            in_lo[a] = p.origin[a] + (at[a] + 0.3) * (double)p.cell;
            in_hi[a] = p.origin[a] + (at[a] + 0.7) * (double)p.cell;
        }
        /* aim near the voxel: its corner region is where the margin matters */
        for (a = 0; a < 3; a++) r.dir[a] = (float)(p.origin[a] + (at[a] + tu_rnd(&st, -0.3f, 1.3f)) * p.cell
                                                   - r.org[a]);
        r.tnear = brt_random_u64(&st) % 2 ? 0.0f : tu_rnd(&st, 0, 1);
        r.tfar = INFINITY;
        says = brt_inner_occludes(dag, &p, &r);
        box_interval(&r, out_lo, out_hi, &t0, &t1);
        box_interval(&r, in_lo, in_hi, &u0, &u1);
        yes += (uint32_t)says;
        core_rays += u0 < u1;
        if (says && !(t0 < t1))
            test_fail_at(__FILE__, __LINE__, "ray %u (seed %llu) misses the voxel's core after tnear, "
                         "yet the cast says occluded", i, (unsigned long long)test_seed());
        if (!says && u0 < u1)
            test_fail_at(__FILE__, __LINE__, "ray %u (seed %llu) runs through the core after tnear, "
                         "the cast says clear: org %a %a %a dir %a %a %a tnear %a", i, (unsigned long long)test_seed(),
                         r.org[0], r.org[1], r.org[2], r.dir[0], r.dir[1], r.dir[2], r.tnear);
    }
    EXPECT(yes > 1000 && core_rays > 1000, "%u rays stopped, %u through the core", yes, core_rays);
    brt_svdag_free(dag);
}

/* The walls are only the closed components' voxels: a ball inside a box
** of open sheets still has inner voxels (open geometry walls nothing in,
** and does not spoil the closed ball). */
static void test_open_geometry_walls_nothing(void)
{
    uint64_t st = test_seed(), voxels = 0;
    float c[3] = {0.5f, 0.5f, 0.5f};
    uint32_t closed = 0, i, v[8];
    brt_svdag *dag = NULL;
    brt_proxy p;
    tu_scene s;
    memset(&s, 0, sizeof s);
    for (i = 0; i < 8; i++) v[i] = tu_add_vertex(&s, (float)(i & 1), (float)(i >> 1 & 1), (float)(i >> 2));
    /* five faces of the unit cube (the top left open) */
    tu_add_triangle(&s, v[0], v[1], v[3]); tu_add_triangle(&s, v[0], v[3], v[2]);
    tu_add_triangle(&s, v[0], v[4], v[5]); tu_add_triangle(&s, v[0], v[5], v[1]);
    tu_add_triangle(&s, v[0], v[2], v[6]); tu_add_triangle(&s, v[0], v[6], v[4]);
    tu_add_triangle(&s, v[1], v[5], v[7]); tu_add_triangle(&s, v[1], v[7], v[3]);
    tu_add_triangle(&s, v[2], v[3], v[7]); tu_add_triangle(&s, v[2], v[7], v[6]);
    CHECK(brt_svdag_create(&dag) == BRT_OK, "no pool");
    CHECK(inner_of(&s, 32, dag, &p, &voxels, &closed) == BRT_OK, "inner voxelization failed");
    EXPECT(voxels == 0 && closed == 0, "an open box: %llu inner voxels, %u closed triangles",
           (unsigned long long)voxels, closed);
    brt_svdag_free(dag);
    CHECK(brt_svdag_create(&dag) == BRT_OK, "no pool");
    add_ball(&s, c, 0.3f, 6, 0.0f, &st);
    CHECK(inner_of(&s, 32, dag, &p, &voxels, &closed) == BRT_OK, "inner voxelization failed");
    EXPECT(voxels > 0 && closed == s.tcount - 10, "a ball in an open box: %llu inner voxels, %u of "
           "%u triangles closed", (unsigned long long)voxels, closed, s.tcount - 10);
    brt_svdag_free(dag);
    tu_scene_free(&s);
}

/* A scene of balls: occlusion bytes identical across brute force, direct,
** batched with inner proxies on and off, at memory limits; inner proxies
** stop rays when each ball lies in one bucket of the build (whether or not
** batching points cut it), and none when the buckets cut the balls (their
** components are open in each). */
static void check_scene(const tu_scene *s, uint32_t point_tris, uint32_t bucket_tris, int expect_stopped,
                        const char *what)
{
    static const uint64_t limits[] = {0, 1};
    brt_mesh mesh = tu_mesh_view(s);
    brt_scene_options sopt;
    brt_scene *scene = NULL;
    brt_ray *rays = malloc(6000 * sizeof *rays);
    uint8_t *exact = malloc(6000), *got = malloc(6000);
    uint64_t st = test_seed() + 5;
    brt_error err;
    size_t i, k;
    CHECK(rays && exact && got, "out of memory");
    for (i = 0; i < 6000; i++) {
        make_ray(s, &st, &rays[i]);
        exact[i] = (uint8_t)tu_brute_occluded(s, &rays[i]);
    }
    memset(&sopt, 0, sizeof sopt);
    sopt.point_tris = point_tris;
    sopt.proxy_res = 32;
    brt_test_build_sizes(0, bucket_tris);
    CHECK(brt_scene_build(&mesh, &sopt, 0, tu_scratch("inner.brs"), &err) == BRT_OK, "%s", err.message);
    CHECK(brt_scene_open(tu_scratch("inner.brs"), &scene, &err) == BRT_OK, "%s", err.message);
    for (k = 0; k < 4 && !test_failed(); k++) {
        brt_trace_options topt;
        brt_stats stats;
        memset(&topt, 0, sizeof topt);
        topt.memory_limit = limits[k & 1];
        topt.no_inner = (int)(k >> 1);
        CHECK(brt_scene_occluded(scene, &topt, rays, 6000, got, &stats, &err) == BRT_OK, "%s", err.message);
        for (i = 0; i < 6000; i++)
            if (got[i] != exact[i]) {
                test_fail_at(__FILE__, __LINE__, "%s, limit %llu, inner %s: ray %zu occluded %u, "
                             "brute force %u (seed %llu)", what, (unsigned long long)topt.memory_limit,
                             topt.no_inner ? "off" : "on", i, got[i], exact[i],
                             (unsigned long long)test_seed());
                break;
            }
        if (topt.no_inner || !expect_stopped)
            EXPECT(stats.occlusion_inner_stopped == 0, "%s, inner %s: %llu rays stopped", what,
                   topt.no_inner ? "off" : "on", (unsigned long long)stats.occlusion_inner_stopped);
        else
            EXPECT(stats.occlusion_inner_stopped > stats.occlusion_hits / 10,
                   "%s: inner proxies stopped %llu of %llu occluded rays", what,
                   (unsigned long long)stats.occlusion_inner_stopped,
                   (unsigned long long)stats.occlusion_hits);
    }
    brt_scene_close(scene);
    free(rays);
    free(exact);
    free(got);
}

static void test_scene_balls(void)
{
    uint64_t st = test_seed();
    float c[3];
    tu_scene s;
    int i;
    memset(&s, 0, sizeof s);
    for (i = 0; i < 8; i++) {   /* 8 balls of 192 triangles, apart on a lattice */
        c[0] = 0.25f + 0.5f * (float)(i & 1);
        c[1] = 0.25f + 0.5f * (float)(i >> 1 & 1);
        c[2] = 0.25f + 0.5f * (float)(i >> 2);
        add_ball(&s, c, 0.18f, 4, 0.05f, &st);
    }
    check_scene(&s, 192, 0, 1, "a ball per batching point");
    check_scene(&s, 100, 0, 1, "balls cut by batching points, one bucket");
    check_scene(&s, 100, 100, 0, "balls cut by buckets");
    tu_scene_free(&s);
}

/* trace --occlusion: the same file direct, batched, inner on and off. */
static void test_trace_files(void)
{
    static const char *const runs[] = {"--batched --point-tris 192 --proxy-res 32",
                                       "--batched --point-tris 192 --proxy-res 32 --no-inner",
                                       "--batched --point-tris 192 --proxy-res 32 --memory 1"};
    uint64_t st = test_seed();
    float c[3];
    tu_scene s;
    brt_ray *rays = malloc(3000 * sizeof *rays);
    unsigned char *direct, *other;
    size_t n_direct, n_other, i;
    brt_error err;
    FILE *f;
    memset(&s, 0, sizeof s);
    for (i = 0; i < 4; i++) {
        c[0] = 0.25f + 0.5f * (float)(i & 1);
        c[1] = 0.25f + 0.5f * (float)(i >> 1 & 1);
        c[2] = 0.5f;
        add_ball(&s, c, 0.2f, 4, 0.05f, &st);
    }
    f = fopen(tu_scratch("inner.obj"), "w");
    CHECK(f && rays, "cannot write");
    for (i = 0; i < s.vcount; i++)
        fprintf(f, "v %.9g %.9g %.9g\n", s.pos[3 * i], s.pos[3 * i + 1], s.pos[3 * i + 2]);
    for (i = 0; i < s.tcount; i++)
        fprintf(f, "f %u %u %u\n", s.idx[3 * i] + 1, s.idx[3 * i + 1] + 1, s.idx[3 * i + 2] + 1);
    fclose(f);
    tu_scene_free(&s);
    /* the rays from the file's own (rounded) vertices */
    {
        brt_mesh mesh;
        CHECK(brt_mesh_load(tu_scratch("inner.obj"), &mesh, &err) == BRT_OK, "%s", err.message);
        s.pos = mesh.positions;
        s.idx = mesh.indices;
        s.tcount = mesh.triangle_count;
        s.vcount = mesh.vertex_count;
        for (i = 0; i < 3000; i++) make_ray(&s, &st, &rays[i]);
        brt_mesh_free(&mesh);
    }
    CHECK(brt_rays_write(tu_scratch("inner.rays"), rays, 3000, &err) == BRT_OK, "%s", err.message);
    free(rays);
    CHECK(tu_run("trace @/inner.obj @/inner.rays @/direct.occ --occlusion") == 0, "trace failed");
    direct = tu_slurp(tu_scratch("direct.occ"), &n_direct);
    CHECK(direct && n_direct == 3000, "no occlusion file");
    for (i = 0; i < sizeof runs / sizeof *runs && !test_failed(); i++) {
        char *json;
        CHECK(tu_run("trace @/inner.obj @/inner.rays @/other.occ --occlusion --scene @/inner%zu.brs "
                     "--stats @/inner.json %s", i, runs[i]) == 0, "trace %s failed", runs[i]);
        other = tu_slurp(tu_scratch("other.occ"), &n_other);
        EXPECT(other && n_other == n_direct && memcmp(other, direct, n_direct) == 0,
               "trace --occlusion %s: not the bytes of --direct", runs[i]);
        json = (char *)tu_slurp(tu_scratch("inner.json"), NULL);
        EXPECT(json && strstr(json, "\"occlusion_inner_stopped\": ") != NULL &&
               (strstr(json, "\"occlusion_inner_stopped\": 0,") != NULL) == (i == 1),
               "trace %s: occlusion_inner_stopped in the JSON", runs[i]);
        free(json);
        free(other);
    }
    free(direct);
}

/* render: the island out of core with next-event estimation, inner
** proxies on and off: the same image, and shadow rays stopped only when on. */
static void test_render_inner(void)
{
    static const char *const runs[] = {"", "--no-inner"};
    unsigned char *png[2];
    size_t size[2], k;
    for (k = 0; k < 2; k++) {
        char *json;
        CHECK(tu_run("render island --scale 0.2 --point-tris 2000 --spp 2 --width 48 --height 27 "
                     "--memory 25%% --scene @/inner-island.brs --out @/inner%zu.png --stats @/inner%zu.json %s",
                     k, k, runs[k]) == 0, "render %s failed", runs[k]);
        json = (char *)tu_slurp(tu_scratch(k ? "inner1.json" : "inner0.json"), NULL);
        EXPECT(json && (strstr(json, "\"occlusion_inner_stopped\": 0,") == NULL) == (k == 0),
               "render %s: occlusion_inner_stopped", runs[k]);
        free(json);
        png[k] = tu_slurp(tu_scratch(k ? "inner1.png" : "inner0.png"), &size[k]);
    }
    EXPECT(png[0] && png[1] && size[0] == size[1] && memcmp(png[0], png[1], size[0]) == 0,
           "render: the image changes with --no-inner");
    free(png[0]);
    free(png[1]);
}

/* The built-in scenes have closed parts for the inner proxies: the crown
** entirely; in the landscape and the island baked (their foliage is lone
** triangles, open) the terrain with its skirt and floor, the land masses,
** rocks and trunks.  Shares at about 20 thousand triangles, seed 1. */
static void test_builtin_closed_parts(void)
{
    static const struct { const char *name; double scale, least; } scenes[] = {
        {"crown", 0.2, 1.0}, {"landscape", 0.2 / 64, 0.2}, {"island", 0.2 / 40, 0.3}};
    size_t k;
    for (k = 0; k < 3; k++) {
        brt_mesh mesh;
        brt_error err;
        brt_solids *solids = NULL;
        float *corners = NULL;
        uint32_t closed = 0;
        CHECK(ex_scene_generate(scenes[k].name, scenes[k].scale, 1, &mesh, &err) == BRT_OK, "%s", err.message);
        if (solids_of(mesh.positions, mesh.indices, mesh.triangle_count, &solids, &corners) == BRT_OK)
            closed = brt_solids_triangles(solids);
        EXPECT(closed >= scenes[k].least * mesh.triangle_count,
               "%s: %u of %u triangles in closed components, expected at least %.0f %%",
               scenes[k].name, closed, mesh.triangle_count, 100 * scenes[k].least);
        brt_solids_free(solids);
        free(corners);
        brt_mesh_free(&mesh);
    }
}

void suite_inner(void)
{
    test_run("inner: never occluded where brute force is clear, solids and near-solids",
             test_one_sided_api);
    test_run("inner: open geometry walls nothing in", test_open_geometry_walls_nothing);
    test_run("inner: the cast keeps its margin and tnear", test_core_margin);
    test_run("inner: batched occlusion == brute force, inner on/off, solids cut by points and buckets",
             test_scene_balls);
    test_run("inner: trace --occlusion files direct == batched, inner on and off", test_trace_files);
    test_run("inner: built-in scenes have closed parts", test_builtin_closed_parts);
    test_run("inner: render, the same image with and without inner proxies", test_render_inner);
}
