/*
** tests/test_bvh.c -- the triangle BVH against its exact oracle.
**
** The oracle is a brute-force loop over brt_intersect_triangle with the
** tie-break of brt_hit_is_closer; the BVH shares the test's arithmetic, so
** every ray must give the same hit record byte for byte (memcmp), also
** when the hit record carries a previous hit in.  Scenes: random soups,
** the shared real meshes, and adversarial sets (coplanar, grids,
** duplicates, slivers, zero-area, tiny and huge coordinates).  Rays:
** camera, random, bounce (from surface points), axis-parallel.  Plus
** watertightness on closed meshes, degenerate rays, the blob format under
** corruption, and the empty BVH.  brt_bvh_check runs after every build.
*/
#include "test.h"
#include "batchrt.h"
#include "util.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* ===================================================================== */
/* The oracle and the comparison                                         */
/* ===================================================================== */


/* brt_bvh_intersect_normal: the same hit, and the header's normal
** (v1-v0) x (v2-v0) of that triangle; untouched on a miss. */
static int compare_normal(const tu_scene *s, const uint32_t *prim_ids, const brt_bvh *bvh,
                          const brt_ray *ray, const brt_hit *want)
{
    float got[3] = {7, 7, 7}, expect[3] = {7, 7, 7};
    brt_hit h;
    int a;
    brt_hit_clear(&h);
    brt_bvh_intersect_normal(bvh, ray, &h, got);
    if (memcmp(&h, want, sizeof h) != 0) return 0;
    if (want->prim != BRT_NO_PRIM) {
        const float *v0, *v1, *v2;
        uint32_t tri = want->prim;
        if (prim_ids)   /* the triangle that reports this number */
            for (tri = 0; tri < s->tcount && prim_ids[tri] != want->prim; tri++) continue;
        if (tri >= s->tcount) return 0;
        v0 = tu_vertex(s, tri, 0);
        v1 = tu_vertex(s, tri, 1);
        v2 = tu_vertex(s, tri, 2);
        for (a = 0; a < 3; a++) {
            const int b = (a + 1) % 3, c = (a + 2) % 3;
            expect[a] = (v1[b] - v0[b]) * (v2[c] - v0[c]) - (v1[c] - v0[c]) * (v2[b] - v0[b]);
        }
    }
    return memcmp(got, expect, sizeof got) == 0;
}

/* One ray against the oracle: from a miss, with the normal, from a
** carried-in hit that is the answer itself with a higher prim (so ties
** must go to the lower), and any-hit.  Returns 0 (after recording a failure) on a mismatch. */
static int compare_ray(const tu_scene *s, const uint32_t *prim_ids,
                       const brt_bvh *bvh, const brt_ray *ray, const char *what,
                       size_t n)
{
    brt_hit want, got, carried;
    brt_hit_clear(&want);
    brt_hit_clear(&got);
    tu_brute_force(s, prim_ids, ray, &want);
    brt_bvh_intersect(bvh, ray, &got);
    if (memcmp(&want, &got, sizeof want) != 0) {
        test_fail_at(__FILE__, __LINE__, "%s ray %zu (o %a %a %a d %a %a %a [%a,%a]): "
                     "bvh t=%a prim=%u u=%a v=%a, brute force t=%a prim=%u u=%a v=%a",
                     what, n, ray->org[0], ray->org[1], ray->org[2], ray->dir[0], ray->dir[1],
                     ray->dir[2], ray->tnear, ray->tfar, got.t, (unsigned)got.prim, got.u, got.v,
                     want.t, (unsigned)want.prim, want.u, want.v);
        return 0;
    }
    if (brt_bvh_occluded(bvh, ray) != (want.prim != BRT_NO_PRIM)) {
        test_fail_at(__FILE__, __LINE__, "%s ray %zu: occluded disagrees with closest hit", what, n);
        return 0;
    }
    if (!compare_normal(s, prim_ids, bvh, ray, &want)) {
        test_fail_at(__FILE__, __LINE__, "%s ray %zu: brt_bvh_intersect_normal disagrees", what, n);
        return 0;
    }
    if (want.prim == BRT_NO_PRIM || want.prim == BRT_NO_PRIM - 1) return 1;
    /* The oracle's answer is the least hit of a set; adding a worse one
    ** (same t, higher prim) as the carried-in hit leaves it unchanged. */
    carried = want;
    carried.prim++;
    carried.u = carried.v = 0.5f;
    brt_bvh_intersect(bvh, ray, &carried);
    if (memcmp(&carried, &want, sizeof want) != 0) {
        test_fail_at(__FILE__, __LINE__, "%s ray %zu: carried-in hit: bvh prim %u, brute force %u",
                     what, n, (unsigned)carried.prim, (unsigned)want.prim);
        return 0;
    }
    return 1;
}

static brt_bvh *build_checked(const tu_scene *s, const uint32_t *prim_ids)
{
    brt_bvh *bvh = NULL;
    brt_error err;
    brt_result r = brt_bvh_build(s->pos, s->idx, s->tcount, prim_ids, &bvh);
    err.message[0] = 0;
    if (r != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "build: %s", brt_result_string(r));
        return NULL;
    }
    r = brt_bvh_check(bvh, &err);
    if (r != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "check: %s", err.message);
        brt_bvh_free(bvh);
        return NULL;
    }
    if (brt_bvh_triangle_count(bvh) != s->tcount) {
        test_fail_at(__FILE__, __LINE__, "triangle count %u, expected %u",
                     (unsigned)brt_bvh_triangle_count(bvh), (unsigned)s->tcount);
        brt_bvh_free(bvh);
        return NULL;
    }
    return bvh;
}

/* The BVH read in place from its blob (the walk over quantized nodes,
** batching points' walk) against the one built in memory (the resident
** walk, compared with brute force): the same closest hit, normal and
** occlusion, byte for byte.  Returns 0 after recording a failure. */
static int compare_walks(const brt_bvh *built, const brt_bvh *opened, const brt_ray *ray,
                         const char *what, size_t n)
{
    brt_hit a, b;
    float na[3] = {7, 7, 7}, nb[3] = {7, 7, 7};
    brt_hit_clear(&a);
    brt_hit_clear(&b);
    brt_bvh_intersect_normal(built, ray, &a, na);
    brt_bvh_intersect_normal(opened, ray, &b, nb);
    if (memcmp(&a, &b, sizeof a) == 0 && memcmp(na, nb, sizeof na) == 0 &&
        brt_bvh_occluded(built, ray) == brt_bvh_occluded(opened, ray))
        return 1;
    test_fail_at(__FILE__, __LINE__, "%s ray %zu: the blob's walk (t=%a prim %u) differs from "
                 "the resident walk (t=%a prim %u)", what, n, b.t, (unsigned)b.prim, a.t,
                 (unsigned)a.prim);
    return 0;
}

/* The BVH opened from bvh's blob (blob in *mem, to free), or NULL after
** recording a failure. */
static brt_bvh *open_copy(const brt_bvh *bvh, uint32_t prim_limit, void **mem)
{
    const size_t size = brt_bvh_blob_size(bvh);
    brt_bvh *opened = NULL;
    brt_error err;
    if (posix_memalign(mem, 64, size) != 0) {
        test_fail_at(__FILE__, __LINE__, "out of memory for a blob");
        return NULL;
    }
    brt_bvh_blob_write(bvh, *mem);
    if (brt_bvh_blob_open(*mem, size, prim_limit, &opened, &err) != BRT_OK)
        test_fail_at(__FILE__, __LINE__, "open: %s", err.message);
    return opened;
}

/* Builds and compares rays_per_kind rays of every kind, for the built
** BVH and its blob opened; stops at the first mismatch. */
static void compare_scene(const tu_scene *s, const uint32_t *prim_ids,
                          size_t rays_per_kind, uint64_t seed, const char *what)
{
    brt_bvh *bvh = build_checked(s, prim_ids), *opened = NULL;
    void *mem = NULL;
    float lo[3], hi[3];
    uint64_t st = seed;
    char label[128];
    int kind;
    size_t n;
    if (!bvh) return;
    opened = open_copy(bvh, BRT_NO_PRIM, &mem);
    tu_scene_bounds(s, lo, hi);
    for (kind = 0; kind < TU_RAY_KINDS && opened; kind++) {
        snprintf(label, sizeof label, "%s, %s", what, tu_kind_name[kind]);
        for (n = 0; n < rays_per_kind; n++) {
            brt_ray ray;
            tu_make_ray(s, lo, hi, kind, &st, &ray);
            if (!compare_ray(s, prim_ids, bvh, &ray, label, n) ||
                !compare_walks(bvh, opened, &ray, label, n))
                goto done;
        }
    }
done:
    brt_bvh_free(opened);
    free(mem);
    brt_bvh_free(bvh);
}

/* The resident layout is all checked: brt_bvh_check rejects every single
** flipped bit of it (boxes, children, counts, masks, padding, corners,
** numbers, unused lanes), and accepts it again once the bit is back. */
static void test_resident_check(void)
{
    uint64_t st = test_seed() ^ 47;
    tu_scene s = {0};
    brt_bvh *bvh;
    brt_error err;
    size_t bytes = 0;
    int i;
    tu_random_soup(&s, &st, 300, 0.1f);
    bvh = build_checked(&s, NULL);
    if (!bvh) { tu_scene_free(&s); return; }
    for (i = 0; i < 2000 && !test_failed(); i++) {
        const uint64_t at = brt_random_u64(&st);
        bytes = brt_bvh_damage_resident(bvh, at);
        EXPECT(brt_bvh_check(bvh, &err) == BRT_ECHECK, "flip %d (byte %zu of %zu) accepted", i,
               bytes ? (size_t)(at % bytes) : 0, bytes);
        brt_bvh_damage_resident(bvh, at);
    }
    EXPECT(bytes > 0, "the built BVH has no resident layout");
    CHECK(brt_bvh_check(bvh, &err) == BRT_OK, "check after the flips: %s", err.message);
    brt_bvh_free(bvh);
    tu_scene_free(&s);
}

/* ===================================================================== */
/* Soups and adversarial sets                                            */
/* ===================================================================== */

static void test_random_soups(void)
{
    uint64_t st = test_seed();
    static const uint32_t sizes[] = {1, 2, 5, 9, 33, 200, 3000};
    size_t i;
    for (i = 0; i < sizeof sizes / sizeof *sizes && !test_failed(); i++) {
        tu_scene s = {0};
        tu_random_soup(&s, &st, sizes[i], 0.05f + 0.2f * brt_random_float(&st));
        compare_scene(&s, NULL, 300, brt_random_u64(&st), "soup");
        tu_scene_free(&s);
    }
}

/* A soup of 25,000 triangles has 75,000 distinct corners: beyond the
** 65,536 that 16-bit corner offsets reach from one base, so later nodes
** must move their vertex_base (and store again the older corners they
** share).  The checker and brute force see wrong corners at once. */
static void test_vertex_window(void)
{
    uint64_t st = test_seed() ^ 5;
    tu_scene s = {0};
    tu_random_soup(&s, &st, 25000, 0.02f);
    compare_scene(&s, NULL, 600, brt_random_u64(&st), "vertex window");
    tu_scene_free(&s);
}

/* prim_ids other than the identity must be reported (and tie-broken). */
static void test_prim_ids(void)
{
    uint64_t st = test_seed() ^ 7;
    tu_scene s = {0};
    uint32_t *ids, i;
    tu_random_soup(&s, &st, 500, 0.1f);
    ids = malloc(s.tcount * sizeof *ids);
    for (i = 0; i < s.tcount; i++) ids[i] = 1000000u + 3u * (s.tcount - i);
    compare_scene(&s, ids, 300, st, "prim ids");
    free(ids);
    tu_scene_free(&s);
}

static void test_coplanar(void)
{
    uint64_t st = test_seed() ^ 11;
    tu_scene s = {0};
    uint32_t i;
    for (i = 0; i < 2000; i++) {
        const float x = tu_rnd(&st, 0, 1), y = tu_rnd(&st, 0, 1);
        tu_add_triangle(&s, tu_add_vertex(&s, x, y, 0.5f), tu_add_vertex(&s, x + tu_rnd(&st, 0, 0.1f), y, 0.5f),
                     tu_add_vertex(&s, x, y + tu_rnd(&st, 0, 0.1f), 0.5f));
    }
    compare_scene(&s, NULL, 400, st, "coplanar");
    tu_scene_free(&s);
}

/* Unit squares on integer coordinates in the three axis planes: axis rays
** through grid lines and vertices hit shared edges exactly. */
static void axis_grid(tu_scene *s, int n)
{
    int i, j, a;
    for (a = 0; a < 3; a++)
        for (i = 0; i < n; i++)
            for (j = 0; j < n; j++) {
                float p[4][3];
                uint32_t v[4];
                int k;
                for (k = 0; k < 4; k++) {
                    p[k][a] = (float)(n / 2);
                    p[k][(a + 1) % 3] = (float)(i + (k == 1 || k == 2));
                    p[k][(a + 2) % 3] = (float)(j + (k >= 2));
                    v[k] = tu_add_vertex(s, p[k][0], p[k][1], p[k][2]);
                }
                tu_add_triangle(s, v[0], v[1], v[2]);
                tu_add_triangle(s, v[0], v[2], v[3]);
            }
}

static void test_axis_grid(void)
{
    uint64_t st = test_seed() ^ 13;
    tu_scene s = {0};
    brt_bvh *bvh;
    int x, y, a;
    size_t n = 0;
    axis_grid(&s, 12);
    compare_scene(&s, NULL, 300, st, "grid");
    bvh = build_checked(&s, NULL);
    if (!bvh) { tu_scene_free(&s); return; }
    /* axis rays both ways through every lattice point and half-lattice
    ** point (both ways: each sees the squares wound the other way round) */
    for (a = 0; a < 6 && !test_failed(); a++)
        for (x = 0; x <= 24; x++)
            for (y = 0; y <= 24; y++) {
                const int axis = a % 3;
                const float sign = a < 3 ? 1.0f : -1.0f;
                brt_ray r = {{0, 0, 0}, {0, 0, 0}, 0.0f, INFINITY};
                r.org[axis] = 6.0f - 11.0f * sign;
                r.org[(axis + 1) % 3] = 0.5f * (float)x;
                r.org[(axis + 2) % 3] = 0.5f * (float)y;
                r.dir[axis] = sign;
                if (!compare_ray(&s, NULL, bvh, &r, "grid lattice", n++)) goto done;
                {   /* the closed squares of plane axis cover [0,12]^2: a hit at t = 11 */
                    brt_hit h;
                    brt_hit_clear(&h);
                    brt_bvh_intersect(bvh, &r, &h);
                    CHECK(h.prim != BRT_NO_PRIM && h.t == 11.0f && tu_vertex(&s, h.prim, 0)[axis] == 6.0f,
                          "lattice ray along axis %d (%+g) through (%g, %g): t=%g prim %u, expected "
                          "a square of plane %d at t = 11", axis, sign, 0.5 * x, 0.5 * y, h.t,
                          (unsigned)h.prim, axis);
                }
            }
done:
    brt_bvh_free(bvh);
    tu_scene_free(&s);
}

static void test_duplicates(void)
{
    uint64_t st = test_seed() ^ 17;
    tu_scene s = {0};
    uint32_t i, n;
    tu_random_soup(&s, &st, 300, 0.1f);
    n = s.tcount;
    for (i = 0; i < 2 * n; i++)   /* the same triangles twice more */
        tu_add_triangle(&s, s.idx[3 * (i % n)], s.idx[3 * (i % n) + 1], s.idx[3 * (i % n) + 2]);
    compare_scene(&s, NULL, 300, st, "duplicates");
    tu_scene_free(&s);
}

/* Slivers (third vertex within 1e-4..1e-7 of the opposite edge) and
** zero-area triangles (collinear or repeated vertices). */
static void test_slivers_and_zero_area(void)
{
    uint64_t st = test_seed() ^ 19;
    tu_scene s = {0};
    uint32_t i;
    for (i = 0; i < 3000; i++) {
        float a[3], b[3], m[3];
        const float eps = (i % 3 == 2) ? 0.0f : (i % 3 ? 1e-4f : 1e-7f);
        int k;
        for (k = 0; k < 3; k++) { a[k] = tu_rnd(&st, 0, 1); b[k] = a[k] + tu_rnd(&st, -0.2f, 0.2f); }
        for (k = 0; k < 3; k++) m[k] = 0.5f * (a[k] + b[k]) + tu_rnd(&st, -eps, eps);
        if (i % 7 == 0) memcpy(m, a, sizeof m);
        tu_add_triangle(&s, tu_add_vertex(&s, a[0], a[1], a[2]), tu_add_vertex(&s, b[0], b[1], b[2]),
                     tu_add_vertex(&s, m[0], m[1], m[2]));
    }
    compare_scene(&s, NULL, 400, st, "slivers");
    tu_scene_free(&s);
}

/* Rays that graze triangles (nearly in their plane), where Woop's T/det
** is least accurate: the BVH still equals brute force, every hit lies in
** the box span of its own triangle (so every enclosing box is entered no
** later -- what makes pruning exact), and its t is close to the exact
** distance to the plane computed in long double. */
static void test_grazing(void)
{
    uint64_t st = test_seed() ^ 23;
    tu_scene s = {0};
    brt_bvh *bvh;
    uint32_t i, hits = 0;
    tu_random_soup(&s, &st, 2000, 0.1f);
    bvh = build_checked(&s, NULL);
    CHECK(bvh, "build failed");
    for (i = 0; i < 20000 && !test_failed(); i++) {
        const uint32_t tri = (uint32_t)(brt_random_u64(&st) % s.tcount);
        const float *v0 = tu_vertex(&s, tri, 0), *v1 = tu_vertex(&s, tri, 1), *v2 = tu_vertex(&s, tri, 2);
        const float tilt = powf(10.0f, -tu_rnd(&st, 1.0f, 7.0f));
        float e1[3], e2[3], n[3], lo[3], hi[3], u = tu_rnd(&st, 0, 1), v = tu_rnd(&st, 0, 1 - u), len = 0;
        long double ld_num = 0, ld_den = 0;
        brt_ray ray;
        brt_ray_prep prep;
        brt_hit hit;
        float entry, exit;
        int a;
        for (a = 0; a < 3; a++) { e1[a] = v1[a] - v0[a]; e2[a] = v2[a] - v0[a]; }
        n[0] = e1[1] * e2[2] - e1[2] * e2[1];
        n[1] = e1[2] * e2[0] - e1[0] * e2[2];
        n[2] = e1[0] * e2[1] - e1[1] * e2[0];
        for (a = 0; a < 3; a++) len += n[a] * n[a];
        if (!(len > 0)) continue;
        len = sqrtf(len);
        /* Along edge 1, tilted out of the plane by `tilt`, from outside. */
        for (a = 0; a < 3; a++) {
            ray.dir[a] = e1[a] + tilt * n[a] / len;
            ray.org[a] = v0[a] + u * e1[a] + v * e2[a] - 2.0f * ray.dir[a];
        }
        ray.tnear = 0.0f;
        ray.tfar = INFINITY;
        if (!compare_ray(&s, NULL, bvh, &ray, "grazing", i)) break;
        brt_hit_clear(&hit);
        if (!brt_intersect_triangle(&ray, v0, v1, v2, &hit.t, &hit.u, &hit.v)) continue;
        hits++;
        for (a = 0; a < 3; a++) {
            /* The exact normal: products of float differences are exact
            ** in long double's 64-bit mantissa (x87) or at least close. */
            const int b = (a + 1) % 3, c = (a + 2) % 3;
            const long double nl = ((long double)v1[b] - v0[b]) * ((long double)v2[c] - v0[c]) -
                                   ((long double)v1[c] - v0[c]) * ((long double)v2[b] - v0[b]);
            lo[a] = fminf(v0[a], fminf(v1[a], v2[a]));
            hi[a] = fmaxf(v0[a], fmaxf(v1[a], v2[a]));
            ld_num += nl * ((long double)v0[a] - ray.org[a]);
            ld_den += nl * ray.dir[a];
        }
        brt_ray_prepare(&ray, &prep);
        brt_box_pad(lo, hi, lo, hi);
        EXPECT(brt_box_span(&prep, lo, hi, ray.tnear, ray.tfar, &entry, &exit) && entry <= hit.t &&
               hit.t <= exit, "grazing ray %u: t %a outside its triangle's box span [%a, %a]",
               i, hit.t, entry, exit);
        /* Where the exact plane point lies on the triangle, t is its
        ** distance to a few float ulps, whatever the tilt; elsewhere (the
        ** float ray misses the exact triangle: the "hit" is rounding) t is
        ** moved onto the triangle's prism (bvh.c, hit_distance), so the
        ** hit's point lies within PAD_REL of the largest |coordinate| of
        ** the triangle, grown by a few ulps of its distance -- what the
        ** proxies cover. */
        {
            double at[3], c0[3], c1[3], c2[3], reach = 0, plane[3], dlen = 0;
            const long double td = ld_num / ld_den;
            for (a = 0; a < 3; a++) {
                at[a] = ray.org[a] + (double)hit.t * ray.dir[a];
                plane[a] = (double)(ray.org[a] + td * ray.dir[a]);
                c0[a] = v0[a];
                c1[a] = v1[a];
                c2[a] = v2[a];
                dlen += (double)ray.dir[a] * ray.dir[a];
                reach = fmax(reach, fmax(fabs((double)ray.org[a]), fmax(fabs(c0[a]), fmax(fabs(c1[a]), fabs(c2[a])))));
            }
            EXPECT(tu_point_triangle_distance(plane, c0, c1, c2) > 1e-9 * reach ||
                   fabsl(hit.t - td) <= 1e-6L * fabsl(td),
                   "grazing ray %u (tilt %g): t %.9g, plane distance %.9Lg", i, tilt, hit.t, td);
            EXPECT(tu_point_triangle_distance(at, c0, c1, c2) <= 2.0 * 16.0 * FLT_EPSILON * reach +
                   4.0 * FLT_EPSILON * fabs((double)hit.t) * sqrt(dlen),
                   "grazing ray %u (tilt %g): its hit point lies %g from the triangle (reach %g)", i, tilt,
                   tu_point_triangle_distance(at, c0, c1, c2), reach);
        }
    }
    EXPECT(hits > 1000, "only %u grazing rays hit their triangle", hits);
    brt_bvh_free(bvh);
    tu_scene_free(&s);
}

/* brt_box_span4 is the top level's box test and must give the same bits
** as brt_box_span lane by lane (the batched walk's keys depend on it):
** random padded boxes, flat boxes, empty lanes (+inf..-inf), coordinates
** from 1e-30 to 1e30, axis-parallel rays with +0 and -0 components, and
** random segments. */
static float random_coordinate(uint64_t *st)
{
    static const float scales[4] = {1.0f, 1e-30f, 1e30f, 1e3f};
    return (2.0f * brt_random_float(st) - 1.0f) * scales[brt_random_u64(st) % 4];
}

static void test_box_span4(void)
{
    uint64_t st = test_seed() + 11;
    unsigned i, lanes_hit = 0;
    for (i = 0; i < 200000 && !test_failed(); i++) {
        float box[6][4], entry4[4], exit4[4];
        brt_ray ray;
        brt_ray_prep prep;
        brt_box_lanes lanes;
        float tmin = brt_random_u64(&st) % 2 ? 0.0f : brt_random_float(&st);
        float tmax = brt_random_u64(&st) % 2 ? INFINITY : tmin + 10.0f * brt_random_float(&st);
        unsigned mask;
        int a, lane;
        for (a = 0; a < 3; a++) {
            ray.org[a] = random_coordinate(&st);
            ray.dir[a] = brt_random_u64(&st) % 4 ? random_coordinate(&st)
                                                  : (brt_random_u64(&st) % 2 ? 0.0f : -0.0f);
        }
        ray.tnear = tmin;
        ray.tfar = tmax;
        brt_ray_prepare(&ray, &prep);
        for (lane = 0; lane < 4; lane++) {
            float lo[3], hi[3];
            for (a = 0; a < 3; a++) {
                float x = random_coordinate(&st), y = brt_random_u64(&st) % 4 ? random_coordinate(&st) : x;
                lo[a] = fminf(x, y);
                hi[a] = fmaxf(x, y);
            }
            brt_box_pad(lo, hi, lo, hi);
            if (brt_random_u64(&st) % 8 == 0)
                for (a = 0; a < 3; a++) { lo[a] = INFINITY; hi[a] = -INFINITY; }
            for (a = 0; a < 3; a++) {
                box[a][lane] = lo[a];
                box[3 + a][lane] = hi[a];
            }
        }
        brt_box_lanes_of(&prep, &lanes);
        mask = brt_box_span4(&lanes, (const float (*)[4])box, tmin, tmax, entry4, exit4);
        for (lane = 0; lane < 4; lane++) {
            float lo[3], hi[3], entry, exit;
            int one;
            for (a = 0; a < 3; a++) {
                lo[a] = box[a][lane];
                hi[a] = box[3 + a][lane];
            }
            one = brt_box_span(&prep, lo, hi, tmin, tmax, &entry, &exit);
            lanes_hit += (unsigned)one;
            EXPECT(one == (int)((mask >> lane) & 1u) && memcmp(&entry, &entry4[lane], 4) == 0 &&
                   memcmp(&exit, &exit4[lane], 4) == 0,
                   "ray %u lane %d: brt_box_span %d [%a, %a], brt_box_span4 %u [%a, %a]", i, lane,
                   one, entry, exit, (mask >> lane) & 1u, entry4[lane], exit4[lane]);
        }
    }
    EXPECT(lanes_hit > 1000, "only %u lanes entered: the test covers too few boxes", lanes_hit);
}

static void test_scales(void)
{
    static const float scale[] = {1e-6f, 1e6f, 1.0f, 1e-6f};
    static const float offset[] = {0.0f, 0.0f, 1e6f, 1.0f};
    uint64_t st = test_seed() ^ 23;
    int i;
    for (i = 0; i < 4 && !test_failed(); i++) {
        tu_scene s = {0};
        char what[64];
        tu_random_soup(&s, &st, 1500, 0.05f);
        axis_grid(&s, 4);
        tu_scene_transform(&s, scale[i], offset[i]);
        snprintf(what, sizeof what, "scale %g offset %g", scale[i], offset[i]);
        compare_scene(&s, NULL, 300, st, what);
        tu_scene_free(&s);
    }
}

/* ===================================================================== */
/* Shared real meshes                                                    */
/* ===================================================================== */

static void compare_shared_mesh(const char *name, size_t rays_per_kind)
{
    const char *path = test_shared_mesh(name);
    brt_mesh mesh;
    brt_error err;
    tu_scene s = {0};
    if (!path) { test_skip("%s: ../shared not found", name); return; }
    if (brt_mesh_load(path, &mesh, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s: %s", name, err.message);
        return;
    }
    s.pos = mesh.positions;
    s.idx = mesh.indices;
    s.vcount = mesh.vertex_count;
    s.tcount = mesh.triangle_count;
    compare_scene(&s, NULL, rays_per_kind, test_seed(), name);
    brt_mesh_free(&mesh);
}

static void test_mesh_bunny_tiny(void) { compare_shared_mesh("bunny_tiny.obj", 500); }
static void test_mesh_bunny(void) { compare_shared_mesh("bunny.obj.gz", 200); }
static void test_mesh_dragon(void) { compare_shared_mesh("dragon.obj.gz", 40); }
static void test_mesh_bmw(void) { compare_shared_mesh("bmw_m6.obj.gz", 40); }
static void test_mesh_crown(void) { compare_shared_mesh("crown.obj.gz", 12); }
static void test_mesh_oahu(void) { compare_shared_mesh("fg_oahu.obj.gz", 20); }

/* ===================================================================== */
/* Watertightness                                                        */
/* ===================================================================== */

/* Icosahedron subdivided `levels` times, vertices pushed to the unit
** sphere and shared between faces (midpoints cached per edge). */
static uint32_t midpoint(tu_scene *s, uint32_t *cache, uint32_t *keys, size_t cap,
                         uint32_t a, uint32_t b)
{
    const uint32_t lo = a < b ? a : b, hi = a < b ? b : a;
    size_t h = ((size_t)lo * 2654435761u ^ hi) % cap;
    float p[3], len;
    int k;
    while (cache[h] != BRT_NO_PRIM) {
        if (keys[2 * h] == lo && keys[2 * h + 1] == hi) return cache[h];
        h = (h + 1) % cap;
    }
    for (k = 0; k < 3; k++) p[k] = s->pos[3 * a + k] + s->pos[3 * b + k];
    len = sqrtf(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    keys[2 * h] = lo;
    keys[2 * h + 1] = hi;
    cache[h] = tu_add_vertex(s, p[0] / len, p[1] / len, p[2] / len);
    return cache[h];
}

static void icosphere(tu_scene *s, int levels)
{
    static const uint32_t faces[20][3] = {
        {0, 11, 5}, {0, 5, 1}, {0, 1, 7}, {0, 7, 10}, {0, 10, 11}, {1, 5, 9}, {5, 11, 4},
        {11, 10, 2}, {10, 7, 6}, {7, 1, 8}, {3, 9, 4}, {3, 4, 2}, {3, 2, 6}, {3, 6, 8},
        {3, 8, 9}, {4, 9, 5}, {2, 4, 11}, {6, 2, 10}, {8, 6, 7}, {9, 8, 1}};
    const float g = 1.6180339887f, n = sqrtf(1.0f + g * g);
    const float base[12][3] = {{-1, g, 0}, {1, g, 0}, {-1, -g, 0}, {1, -g, 0}, {0, -1, g}, {0, 1, g},
                               {0, -1, -g}, {0, 1, -g}, {g, 0, -1}, {g, 0, 1}, {-g, 0, -1}, {-g, 0, 1}};
    int i, l;
    for (i = 0; i < 12; i++) tu_add_vertex(s, base[i][0] / n, base[i][1] / n, base[i][2] / n);
    for (i = 0; i < 20; i++) tu_add_triangle(s, faces[i][0], faces[i][1], faces[i][2]);
    for (l = 0; l < levels; l++) {
        const size_t cap = 8 * (size_t)s->tcount;
        uint32_t *cache = malloc(cap * sizeof *cache), *keys = malloc(2 * cap * sizeof *keys);
        uint32_t *old = s->idx, count = s->tcount, t;
        memset(cache, 0xFF, cap * sizeof *cache);
        s->idx = NULL;
        s->tcount = s->tcap = 0;
        for (t = 0; t < count; t++) {
            const uint32_t a = old[3 * t], b = old[3 * t + 1], c = old[3 * t + 2];
            const uint32_t ab = midpoint(s, cache, keys, cap, a, b);
            const uint32_t bc = midpoint(s, cache, keys, cap, b, c);
            const uint32_t ca = midpoint(s, cache, keys, cap, c, a);
            tu_add_triangle(s, a, ab, ca);
            tu_add_triangle(s, b, bc, ab);
            tu_add_triangle(s, c, ca, bc);
            tu_add_triangle(s, ab, bc, ca);
        }
        free(old); free(cache); free(keys);
    }
}

/* n^3 closed cubes of side `cell` from `origin`; neighbours share faces
** (each shared face is in the mesh twice, with different diagonals). */
static void cube_grid(tu_scene *s, int n, float origin, float cell)
{
    static const int quads[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4},
                                    {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};
    int x, y, z, q, k;
    for (x = 0; x < n; x++)
        for (y = 0; y < n; y++)
            for (z = 0; z < n; z++) {
                uint32_t v[8];
                for (k = 0; k < 8; k++)
                    v[k] = tu_add_vertex(s, origin + cell * (float)(x + (k & 1)),
                                      origin + cell * (float)(y + (k >> 1 & 1)),
                                      origin + cell * (float)(z + (k >> 2 & 1)));
                for (q = 0; q < 6; q++) {
                    const int flip = (x + y + z + q) & 1;
                    const int *f = quads[q];
                    if (flip) {
                        tu_add_triangle(s, v[f[0]], v[f[1]], v[f[2]]);
                        tu_add_triangle(s, v[f[0]], v[f[2]], v[f[3]]);
                    } else {
                        tu_add_triangle(s, v[f[1]], v[f[2]], v[f[3]]);
                        tu_add_triangle(s, v[f[1]], v[f[3]], v[f[0]]);
                    }
                }
            }
}

/* A ray from `from` aimed exactly at `target` on a closed convex surface
** enclosing `from` (or, from outside, crossing into it) must hit there,
** at t = 1 (dir = target - from), give or take rounding: a hit farther
** on is a leak too (from outside, the far side would hide it).  The BVH
** alone is asked: its hits are hits of the shared triangle test, and
** agreement with brute force is the other tests' business.  Counts
** leaks, reports the first. */
static void aim(const brt_bvh *bvh, const float from[3], const float target[3],
                size_t *rays, size_t *leaks)
{
    brt_ray r;
    brt_hit h;
    int a;
    for (a = 0; a < 3; a++) { r.org[a] = from[a]; r.dir[a] = target[a] - from[a]; }
    r.tnear = 0.0f;
    r.tfar = INFINITY;
    brt_hit_clear(&h);
    brt_bvh_intersect(bvh, &r, &h);
    (*rays)++;
    if (h.prim != BRT_NO_PRIM && h.t <= 1.001f) return;
    if ((*leaks)++ == 0)
        test_fail_at(__FILE__, __LINE__, "leak: ray from (%a %a %a) at (%a %a %a) hit nothing "
                     "up to the target (t=%g)", from[0], from[1], from[2], target[0], target[1],
                     target[2], h.t);
}

/* Aims at every vertex and every edge midpoint of every triangle, from an
** inside point and from an outside point beyond the target. */
static void aim_at_features(const tu_scene *s, const brt_bvh *bvh, const float inside[3],
                            uint64_t *st, size_t *rays, size_t *leaks)
{
    uint32_t t;
    int j, a;
    for (t = 0; t < s->tcount; t++)
        for (j = 0; j < 6; j++) {
            const float *p = tu_vertex(s, t, j % 3), *q = tu_vertex(s, t, (j + 1) % 3);
            float target[3], outside[3], jitter[3], w = 0.0f;
            tu_random_unit(st, jitter);
            for (a = 0; a < 3; a++) {
                target[a] = j < 3 ? p[a] : 0.5f * (p[a] + q[a]);
                w += (target[a] - inside[a]) * (target[a] - inside[a]);
            }
            /* beyond the target the ray passes within 0.05*|w| of inside */
            for (a = 0; a < 3; a++)
                outside[a] = inside[a] + 3.0f * (target[a] - inside[a]) + 0.1f * sqrtf(w) * jitter[a];
            aim(bvh, inside, target, rays, leaks);
            aim(bvh, outside, target, rays, leaks);
        }
}

static void test_watertight_icosphere(void)
{
    uint64_t st = test_seed() ^ 29;
    tu_scene s = {0};
    brt_bvh *bvh;
    size_t rays = 0, leaks = 0;
    int i;
    icosphere(&s, 4);
    bvh = build_checked(&s, NULL);
    for (i = 0; bvh && i < 3; i++) {
        float inside[3];
        tu_random_unit(&st, inside);
        inside[0] *= 0.3f; inside[1] *= 0.3f; inside[2] *= 0.3f;
        aim_at_features(&s, bvh, inside, &st, &rays, &leaks);
    }
    EXPECT(leaks == 0, "%zu of %zu rays leaked", leaks, rays);
    brt_bvh_free(bvh);
    tu_scene_free(&s);
}

/* From far away (10^2..10^5 times the sphere's size): the slab distances'
** rounding then comes from the origin's coordinates, not the box's, and
** only the origin's own padding (rule 2) keeps the boxes of a vertex's or
** an edge's triangles from being missed. */
static void test_watertight_far(void)
{
    uint64_t st = test_seed() ^ 67;
    tu_scene s = {0};
    brt_bvh *bvh;
    size_t rays = 0, leaks = 0;
    uint32_t t;
    int j, a;
    icosphere(&s, 2);
    bvh = build_checked(&s, NULL);
    for (t = 0; bvh && t < s.tcount; t++)
        for (j = 0; j < 6; j++) {
            const float *p = tu_vertex(&s, t, j % 3), *q = tu_vertex(&s, t, (j + 1) % 3);
            const float far = powf(10.0f, tu_rnd(&st, 2.0f, 5.0f));
            float target[3], from[3], dir[3];
            tu_random_unit(&st, dir);
            for (a = 0; a < 3; a++) {
                target[a] = j < 3 ? p[a] : 0.5f * (p[a] + q[a]);
                from[a] = target[a] + far * (dir[a] + 2.0f * target[a]);   /* outside */
            }
            aim(bvh, from, target, &rays, &leaks);
        }
    EXPECT(leaks == 0, "%zu of %zu rays leaked", leaks, rays);
    brt_bvh_free(bvh);
    tu_scene_free(&s);
}

static void test_watertight_cubes(void)
{
    uint64_t st = test_seed() ^ 31;
    tu_scene s = {0};
    brt_bvh *bvh;
    size_t rays = 0, leaks = 0;
    const int n = 5;
    const float origin = 0.3f, cell = 0.1f;
    int x, y, z;
    cube_grid(&s, n, origin, cell);
    bvh = build_checked(&s, NULL);
    /* from inside every cube at its own vertices and edge midpoints */
    for (x = 0; bvh && x < n; x++)
        for (y = 0; y < n; y++)
            for (z = 0; z < n; z++) {
                const uint32_t first = (uint32_t)(12 * ((x * n + y) * n + z));
                tu_scene cube = s;
                float inside[3];
                inside[0] = origin + cell * ((float)x + tu_rnd(&st, 0.1f, 0.9f));
                inside[1] = origin + cell * ((float)y + tu_rnd(&st, 0.1f, 0.9f));
                inside[2] = origin + cell * ((float)z + tu_rnd(&st, 0.1f, 0.9f));
                cube.idx = s.idx + 3 * first;   /* this cube's 12 triangles */
                cube.tcount = 12;
                aim_at_features(&cube, bvh, inside, &st, &rays, &leaks);
            }
    EXPECT(leaks == 0, "%zu of %zu rays leaked", leaks, rays);
    brt_bvh_free(bvh);
    tu_scene_free(&s);
}

/* ===================================================================== */
/* Degenerate rays, empty BVH, blobs                                     */
/* ===================================================================== */

static void test_degenerate_rays(void)
{
    uint64_t st = test_seed() ^ 37;
    tu_scene s = {0};
    brt_bvh *bvh;
    const float bad[] = {NAN, INFINITY, -INFINITY};
    const brt_ray good = {{0.5f, 0.5f, -3.0f}, {0.01f, 0.02f, 1.0f}, 0.0f, INFINITY};
    size_t n = 0;
    int c, b;
    tu_random_soup(&s, &st, 400, 0.2f);
    axis_grid(&s, 2);   /* a square at z = 1 covering [0,2]^2: `good` hits */
    bvh = build_checked(&s, NULL);
    if (!bvh) { tu_scene_free(&s); return; }
    for (c = 0; c < 8; c++)
        for (b = 0; b < 3; b++) {
            brt_ray r = good;
            float *field = c < 3 ? &r.org[c] : c < 6 ? &r.dir[c - 3] : c == 6 ? &r.tnear : &r.tfar;
            brt_hit h;
            *field = bad[b];
            if ((c == 7 && b == 1) || (c == 6 && b == 2))
                continue;   /* tfar = +inf, tnear = -inf: ordinary rays */
            if (!compare_ray(&s, NULL, bvh, &r, "bad component", n++)) goto done;
            brt_hit_clear(&h);
            brt_bvh_intersect(bvh, &r, &h);
            CHECK(h.prim == BRT_NO_PRIM, "ray with component %d = %g hit prim %u", c, bad[b],
                  (unsigned)h.prim);
        }
    {
        brt_ray zero = good, reversed = good;
        brt_hit h;
        float t, u, v;
        zero.dir[0] = zero.dir[1] = zero.dir[2] = 0.0f;
        reversed.tnear = 2.0f;
        reversed.tfar = 1.0f;
        CHECK(compare_ray(&s, NULL, bvh, &zero, "zero direction", 0), "zero direction");
        CHECK(compare_ray(&s, NULL, bvh, &reversed, "tnear > tfar", 0), "tnear > tfar");
        brt_hit_clear(&h);
        brt_bvh_intersect(bvh, &good, &h);
        CHECK(h.prim != BRT_NO_PRIM, "the reference ray should hit");
        CHECK(!brt_intersect_triangle(&zero, tu_vertex(&s, h.prim, 0), tu_vertex(&s, h.prim, 1),
                                      tu_vertex(&s, h.prim, 2), &t, &u, &v), "zero direction hit");
        CHECK(!brt_intersect_triangle(&reversed, tu_vertex(&s, h.prim, 0), tu_vertex(&s, h.prim, 1),
                                      tu_vertex(&s, h.prim, 2), &t, &u, &v), "tnear > tfar hit");
    }
done:
    brt_bvh_free(bvh);
    tu_scene_free(&s);
}

/* Exact values on one triangle: Embree's barycentrics, inclusive range. */
static void test_triangle_exact(void)
{
    const float v0[3] = {0, 0, 0}, v1[3] = {4, 0, 0}, v2[3] = {0, 4, 0};
    brt_ray r = {{1, 2, 5}, {0, 0, -1}, 0.0f, INFINITY};
    float t, u, v;
    CHECK(brt_intersect_triangle(&r, v0, v1, v2, &t, &u, &v), "should hit");
    CHECK(t == 5.0f && u == 0.25f && v == 0.5f, "t %g u %g v %g, expected 5 0.25 0.5", t, u, v);
    r.tfar = 5.0f;
    CHECK(brt_intersect_triangle(&r, v0, v1, v2, &t, &u, &v), "t == tfar must count");
    r.tnear = 5.0f;
    CHECK(brt_intersect_triangle(&r, v0, v1, v2, &t, &u, &v), "t == tnear must count");
    r.tfar = nextafterf(5.0f, 0.0f);
    r.tnear = 0.0f;
    CHECK(!brt_intersect_triangle(&r, v0, v1, v2, &t, &u, &v), "t > tfar must not count");
    r.tfar = INFINITY;
    r.dir[2] = 1.0f;
    CHECK(!brt_intersect_triangle(&r, v0, v1, v2, &t, &u, &v), "behind the origin");
}

/* Two triangles where the float edge functions have a 0 that is not 0
** exactly, and the ray from the origin along +z passes just outside.
** First (found by a search of random edges): only the paper's double-precision
** recheck of zero edge functions gets the miss right.  Second, a needle
** (found by a search over vertices a few ulps apart): U = V = 0 in float
** although exactly U > 0 > V; here the ray also misses the needle's box,
** so the hit-distance clamp rejects it too. */
static void test_double_fallback(void)
{
    static const float tri[2][3][3] = {
        {{-0x1.0e1bc8p-4f, 0x1.d20466p-2f, 1}, {0x1.a75536p-1f, 0x1.a69602p-1f, 1},
         {-0x1.a07916p-2f, -0x1.9fbcfap-2f, 1}},
        {{0x1.ffffep+0f, 0x1.ffffe4p+0f, 1}, {0x1.fffff8p-1f, 0x1.fffffep-1f, 1},
         {0x1.000002p+0f, 0x1.000004p+0f, 1}}};
    const brt_ray r = {{0, 0, 0}, {0, 0, 1}, 0.0f, INFINITY};
    float t, u, v;
    int i;
    for (i = 0; i < 2; i++)
        CHECK(!brt_intersect_triangle(&r, tri[i][0], tri[i][1], tri[i][2], &t, &u, &v),
              "triangle %d: a hit at t=%g u=%g v=%g for a ray that passes outside", i, t, u, v);
}

/* ---- rays exactly on edges ------------------------------------------- */

/* The sign of the 2D cross product p x q = p0 q1 - p1 q0 of floats,
** exactly: a product of two floats is exact in double, so comparing the
** two products decides the sign with no rounding at all. */
static int exact_cross_sign(const float p[2], const float q[2])
{
    const double l = (double)p[0] * q[1], r = (double)p[1] * q[0];
    return (l > r) - (l < r);
}

/* The exact answer for a ray along a coordinate axis through the 2D
** origin: it meets the closed triangle whose vertices project to a, b, c
** when the three orientations a x b, b x c, c x a share one sign, zeros
** allowed, and are not all zero (a triangle seen edge-on never hits). */
static int exact_axis_hit(const float p[3][2])
{
    int pos = 0, neg = 0, k;
    for (k = 0; k < 3; k++) {
        const int s = exact_cross_sign(p[k], p[(k + 1) % 3]);
        pos |= s > 0;
        neg |= s < 0;
    }
    return pos != neg;
}

/* A float with only the top `bits` bits of its mantissa kept. */
static float trim_mantissa(float x, int bits)
{
    int e;
    const float m = frexpf(x, &e);
    return ldexpf(floorf(ldexpf(m, bits)) / ldexpf(1.0f, bits), e);
}

/* A random float of either sign with magnitude in [2^-4, 2^4). */
static float wide_float(uint64_t *st)
{
    const float x = ldexpf(tu_rnd(st, 1.0f, 2.0f), (int)(brt_random_u64(st) % 8) - 4);
    return brt_random_u64(st) & 1 ? -x : x;
}

/* Three projected vertices with an edge through or next to the origin:
** b = s c rounded (s < 0: the origin lies on the segment bc, and float
** edge functions often round to 0 while the exact one is not 0), b = s c
** exact (the origin exactly on the edge), a vertex at the origin, or an
** edge on a coordinate axis.  The vertex order is rotated so that U, V
** and W each take the zero. */
static void edge_ray_triangle(uint64_t *st, float p[3][2])
{
    static const float exact_s[] = {-1, -2, -0.5f, -0.25f, -3, -1.5f};
    const int kind = (int)(brt_random_u64(st) % 4), rot = (int)(brt_random_u64(st) % 3);
    float q[3][2];
    int k, i;
    for (k = 0; k < 3; k++)
        for (i = 0; i < 2; i++) q[k][i] = wide_float(st);
    switch (kind) {
    case 0: {
        const float s = -tu_rnd(st, 0.1f, 10.0f);
        q[1][0] = s * q[2][0];
        q[1][1] = s * q[2][1];
        break;
    }
    case 1: {
        const float s = exact_s[brt_random_u64(st) % 6];
        for (i = 0; i < 2; i++) {
            q[2][i] = trim_mantissa(q[2][i], 12);
            q[1][i] = s * q[2][i];
        }
        break;
    }
    case 2:
        q[1][0] = q[1][1] = 0.0f;
        break;
    default: {
        const int axis = (int)(brt_random_u64(st) & 1);
        q[1][axis] = -fabsf(q[1][axis]);
        q[2][axis] = fabsf(q[2][axis]);
        q[1][1 - axis] = q[2][1 - axis] = 0.0f;
        break;
    }
    }
    for (k = 0; k < 3; k++) memcpy(p[k], q[(k + rot) % 3], sizeof p[k]);
}

/* Woop's float edge function of p x q for an axis ray from the origin
** (the shear is 0 and the translation exact): zero or not. */
static int float_cross_is_zero(const float p[2], const float q[2])
{
    const float l = p[0] * q[1], r = p[1] * q[0];
    return l - r == 0.0f;
}

/* Rays along all six axis directions through the 2D origin, against
** triangles with an edge through or next to it: brt_intersect_triangle
** must give the exact answer every time.  This is what the recomputation
** of zero edge functions in double is for (a float 0 that is not 0
** exactly; test_double_fallback holds two found by searches), and what
** the sign test's strict compares are for (an exact 0 counts as
** inside).  The test counts the float zeros it met, so that it fails if
** the generator stops making them. */
/* Edge rays also traced through a BVH of their one triangle (a build
** each, so fewer). */
#define EDGE_BVH_RAYS 6000

static void test_edge_rays(void)
{
    uint64_t st = test_seed() ^ 53;
    unsigned long rays = 0, rounded_zeros = 0, exact_zeros = 0, hits = 0;
    float t, u, v;
    int n;
    for (n = 0; n < 60000 && !test_failed(); n++) {
        const int axis = n % 3, sign = (n / 3) % 2 ? -1 : 1;
        float p[3][2], vert[3][3];
        brt_ray r = {{0, 0, 0}, {0, 0, 0}, 0.0f, INFINITY};
        int k, want, got;
        edge_ray_triangle(&st, p);
        for (k = 0; k < 3; k++) {
            vert[k][(axis + 1) % 3] = p[k][0];
            vert[k][(axis + 2) % 3] = p[k][1];
            vert[k][axis] = tu_rnd(&st, 1.0f, 2.0f) * (float)sign;
        }
        r.org[axis] = -3.0f * (float)sign;
        r.dir[axis] = (float)sign;
        want = exact_axis_hit((const float(*)[2])p);
        got = brt_intersect_triangle(&r, vert[0], vert[1], vert[2], &t, &u, &v);
        if (n < EDGE_BVH_RAYS) {   /* the BVH's filter of four triangles at once too */
            static const uint32_t corners[3] = {0, 1, 2};
            brt_bvh *bvh = NULL;
            brt_hit h;
            brt_hit_clear(&h);
            CHECK(brt_bvh_build(&vert[0][0], corners, 1, NULL, &bvh) == BRT_OK, "build");
            brt_bvh_intersect(bvh, &r, &h);
            EXPECT((h.prim != BRT_NO_PRIM) == want, "BVH: axis %d dir %+d, projected (%a %a) (%a %a) "
                   "(%a %a): %s, exactly %s", axis, sign, p[0][0], p[0][1], p[1][0], p[1][1],
                   p[2][0], p[2][1], h.prim != BRT_NO_PRIM ? "hit" : "miss", want ? "hit" : "miss");
            brt_bvh_free(bvh);
        }
        for (k = 0; k < 3; k++)
            if (float_cross_is_zero(p[k], p[(k + 1) % 3])) {
                if (exact_cross_sign(p[k], p[(k + 1) % 3]) == 0) exact_zeros++;
                else rounded_zeros++;
            }
        rays++;
        hits += (unsigned long)want;
        EXPECT(got == want, "axis %d dir %+d, projected (%a %a) (%a %a) (%a %a): %s, exactly %s",
               axis, sign, p[0][0], p[0][1], p[1][0], p[1][1], p[2][0], p[2][1],
               got ? "hit" : "miss", want ? "hit" : "miss");
    }
    printf("  bvh: edge rays: %lu rays (%lu hit exactly); float edge functions of 0: "
           "%lu exact, %lu by rounding\n", rays, hits, exact_zeros, rounded_zeros);
    EXPECT(rounded_zeros >= 1000 && exact_zeros >= 1000,
           "too few zero edge functions to test their rule: %lu exact, %lu by rounding",
           exact_zeros, rounded_zeros);
}

/* Triangles with a zero cross product in double (collinear or coincident
** vertices) never hit, whatever their float edge functions say: oblique
** rays through their points shear them into slivers of rounding noise
** that often all have one sign. */
static void test_degenerate_triangles(void)
{
    uint64_t st = test_seed() ^ 59;
    int n;
    for (n = 0; n < 10000 && !test_failed(); n++) {
        float v[3][3], target[3], t, u, w;
        const float along = (float)(brt_random_u64(&st) % 5) - 2.0f;   /* v2 = v0 + along e */
        const float at = tu_rnd(&st, -0.5f, 1.5f);                      /* target = v0 + at e */
        brt_ray r;
        int a;
        /* few mantissa bits: v1 and v2 are exact, so the three are collinear */
        for (a = 0; a < 3; a++) {
            v[0][a] = trim_mantissa(tu_rnd(&st, -1.0f, 1.0f), 12);
            v[1][a] = v[0][a] + (n % 7 == 0 ? 0.0f : trim_mantissa(tu_rnd(&st, -1.0f, 1.0f), 8));
            v[2][a] = v[0][a] + along * (v[1][a] - v[0][a]);
            target[a] = v[0][a] + at * (v[1][a] - v[0][a]);
        }
        for (a = 0; a < 3; a++) {
            r.org[a] = target[a] + 4.0f * tu_rnd(&st, -1.0f, 1.0f);
            r.dir[a] = target[a] - r.org[a];
        }
        r.tnear = 0.0f;
        r.tfar = INFINITY;
        EXPECT(!brt_intersect_triangle(&r, v[0], v[1], v[2], &t, &u, &w),
               "degenerate (%a %a %a) (%a %a %a) (%a %a %a), ray (%a %a %a) dir (%a %a %a): hit t=%a",
               v[0][0], v[0][1], v[0][2], v[1][0], v[1][1], v[1][2], v[2][0], v[2][1], v[2][2],
               r.org[0], r.org[1], r.org[2], r.dir[0], r.dir[1], r.dir[2], t);
    }
}

/* A box entered exactly at the closest hit so far is still visited: rays
** start (tnear) exactly on a plane of overlapping triangles, so every
** box's entry and every hit is t = tnear, and the lowest prim must win
** wherever its leaf is in the tree.  An exclusive prune (entry < t) would
** stop at the first leaf. */
static void test_entry_equals_hit(void)
{
    uint64_t st = test_seed() ^ 61;
    int scene, n;
    for (scene = 0; scene < 20 && !test_failed(); scene++) {
        tu_scene s = {0};
        uint32_t i;
        brt_bvh *bvh;
        for (i = 0; i < 64; i++) {   /* most cover the rays' points */
            const float x = tu_rnd(&st, -2.0f, 0.2f), y = tu_rnd(&st, -2.0f, 0.2f);
            const uint32_t a = tu_add_vertex(&s, x, y, 0.0f);
            const uint32_t b = tu_add_vertex(&s, x + 3.0f, y, 0.0f);
            const uint32_t c = tu_add_vertex(&s, x, y + 3.0f, 0.0f);
            tu_add_triangle(&s, a, b, c);
        }
        bvh = build_checked(&s, NULL);
        for (n = 0; bvh && n < 8; n++) {
            brt_ray r = {{0.25f, 0.25f, 10.0f}, {0, 0, -1}, 10.0f, INFINITY};
            r.org[0] = tu_rnd(&st, 0.0f, 0.2f);
            r.org[1] = tu_rnd(&st, 0.0f, 0.2f);
            if (!compare_ray(&s, NULL, bvh, &r, "tnear on the hit plane", (size_t)n)) break;
        }
        brt_bvh_free(bvh);
        tu_scene_free(&s);
    }
}

static void test_nonfinite_vertices(void)
{
    const float bad[] = {NAN, INFINITY, -INFINITY};
    float pos[9] = {0, 0, 0, 1, 0, 0, 0, 1, 0};
    const uint32_t idx[3] = {0, 1, 2};
    brt_bvh *bvh = NULL;
    int i, k;
    for (i = 0; i < 9; i++)
        for (k = 0; k < 3; k++) {
            const float keep = pos[i];
            brt_result r;
            pos[i] = bad[k];
            r = brt_bvh_build(pos, idx, 1, NULL, &bvh);
            pos[i] = keep;
            CHECK(r == BRT_EARG && bvh == NULL, "coordinate %d = %g: got %s", i, bad[k],
                  brt_result_string(r));
        }
}

static void test_empty(void)
{
    brt_bvh *bvh = NULL, *opened = NULL;
    brt_error err;
    brt_ray r = {{0, 0, 0}, {1, 0, 0}, -INFINITY, INFINITY};
    brt_hit h;
    float lo[3], hi[3];
    void *blob;
    CHECK(brt_bvh_build(NULL, NULL, 0, NULL, &bvh) == BRT_OK, "empty build");
    CHECK(brt_bvh_check(bvh, &err) == BRT_OK, "check: %s", err.message);
    brt_hit_clear(&h);
    brt_bvh_intersect(bvh, &r, &h);
    EXPECT(h.prim == BRT_NO_PRIM && h.t == INFINITY, "empty bvh hit");
    EXPECT(!brt_bvh_occluded(bvh, &r), "empty bvh occluded");
    brt_bvh_bounds(bvh, lo, hi);
    EXPECT(lo[0] == INFINITY && hi[0] == -INFINITY, "empty bounds");
    blob = malloc(brt_bvh_blob_size(bvh));
    brt_bvh_blob_write(bvh, blob);
    EXPECT(brt_bvh_blob_open(blob, brt_bvh_blob_size(bvh), 0, &opened, &err) == BRT_OK,
           "empty blob: %s", err.message);
    if (opened) {
        brt_bvh_intersect(opened, &r, &h);
        EXPECT(h.prim == BRT_NO_PRIM, "empty blob hit");
    }
    brt_bvh_free(opened);
    free(blob);
    brt_bvh_free(bvh);
}

/* The blob's layout (see bvh.c): a 64-byte header {magic, nodes,
** vertices, triangles}, then 64-byte nodes: f32 org[3] scale[3] at 0,
** u8 q[6][4] at 24, u32 first_node at 48, first_tri at 52, vertex_base at
** 56, u8 count[4] at 60; then 12-byte vertices, u32 prims, 3 u16 corner
** offsets per triangle. */
#define HEADER_BYTES 64
#define NODE_BYTES 64
#define FIRST_NODE 48
#define FIRST_TRI 52
#define VERTEX_BASE 56
#define COUNT 60
#define MAX_LEAF 16   /* a leaf slot's count is 1..MAX_LEAF (bvh.c) */

static void expect_eformat(const void *blob, size_t size, const char *what)
{
    brt_bvh *b = NULL;
    brt_error err;
    brt_result r = brt_bvh_blob_open(blob, size, UINT32_MAX, &b, &err);
    EXPECT(r == BRT_EFORMAT, "%s: got %s, expected a format error", what, brt_result_string(r));
    brt_bvh_free(b);
}

/* The same, and the message names the check that refused it (a forged
** value must be refused by its own check, before anything reads through
** it). */
static void expect_eformat_saying(const void *blob, size_t size, const char *what, const char *piece)
{
    brt_bvh *b = NULL;
    brt_error err;
    brt_result r = brt_bvh_blob_open(blob, size, UINT32_MAX, &b, &err);
    EXPECT(r == BRT_EFORMAT && strstr(err.message, piece), "%s: got %s (%s), expected a format error '%s'", what,
           brt_result_string(r), r == BRT_OK ? "" : err.message, piece);
    brt_bvh_free(b);
}

static void put_u32(unsigned char *p, size_t offset, uint32_t value)
{
    memcpy(p + offset, &value, 4);
}

static uint32_t get_u32(const unsigned char *p, size_t offset)
{
    uint32_t value;
    memcpy(&value, p + offset, 4);
    return value;
}

static int node_has_leaf(const unsigned char *node)
{
    int slot;
    for (slot = 0; slot < 4; slot++)
        if (node[COUNT + slot] >= 1 && node[COUNT + slot] <= MAX_LEAF) return 1;
    return 0;
}

/* A blob decoded after opening (brt_bvh_decode: the geometry cache's
** layer 8) passes the checker, reports its bytes, and answers every ray
** as the blob walked in place; brt_bvh_walk_prepared answers as the plain
** calls, closest hit (with the normal) and occlusion, on both layouts. */
static void test_decoded_and_prepared(void)
{
    uint64_t st = test_seed() ^ 43;
    tu_scene s = {0};
    brt_bvh *bvh, *quantized = NULL, *decoded = NULL;
    brt_error err;
    unsigned char *blob;
    size_t size, n, before, bytes;
    float lo[3], hi[3];
    tu_random_soup(&s, &st, 3000, 0.05f);
    bvh = build_checked(&s, NULL);
    if (!bvh) { tu_scene_free(&s); return; }
    size = brt_bvh_blob_size(bvh);
    blob = malloc(size);
    brt_bvh_blob_write(bvh, blob);
    CHECK(brt_bvh_blob_open(blob, size, s.tcount, &quantized, &err) == BRT_OK &&
          brt_bvh_blob_open(blob, size, s.tcount, &decoded, &err) == BRT_OK, "open: %s", err.message);
    before = brt_bvh_memory_bytes(decoded);
    bytes = brt_bvh_decoded_bytes(decoded);
    CHECK(brt_bvh_decode(decoded) == BRT_OK, "decode failed");
    EXPECT(bytes > 0 && brt_bvh_memory_bytes(decoded) == before + bytes &&
           brt_bvh_decoded_bytes(decoded) == 0,
           "decoded %zu bytes, memory %zu -> %zu, again %zu", bytes, before,
           brt_bvh_memory_bytes(decoded), brt_bvh_decoded_bytes(decoded));
    EXPECT(brt_bvh_check(decoded, &err) == BRT_OK, "check decoded: %s", err.message);
    tu_scene_bounds(&s, lo, hi);
    for (n = 0; n < 3000 && !test_failed(); n++) {
        const brt_bvh *const layouts[2] = {quantized, decoded};
        brt_ray r;
        brt_ray_prep prep;
        brt_box_lanes lanes;
        brt_hit plain, walked;
        float pn[3] = {0, 0, 0}, wn[3] = {0, 0, 0};
        int k;
        tu_make_ray(&s, lo, hi, (int)(n % TU_RAY_KINDS), &st, &r);
        brt_ray_prepare(&r, &prep);
        brt_box_lanes_of(&prep, &lanes);
        for (k = 0; k < 2; k++) {
            brt_hit_clear(&plain);
            brt_hit_clear(&walked);
            brt_bvh_intersect_normal(layouts[0], &r, &plain, pn);
            if (prep.valid) brt_bvh_walk_prepared(layouts[k], &r, &prep, &lanes, &walked, wn, 0);
            EXPECT(memcmp(&plain, &walked, sizeof plain) == 0 && memcmp(pn, wn, sizeof pn) == 0,
                   "ray %zu, %s layout: the prepared walk's hit differs", n, k ? "decoded" : "quantized");
            EXPECT(brt_bvh_occluded(layouts[0], &r) ==
                   (prep.valid && brt_bvh_walk_prepared(layouts[k], &r, &prep, &lanes, NULL, NULL, 1)),
                   "ray %zu, %s layout: the prepared walk's occlusion differs", n,
                   k ? "decoded" : "quantized");
        }
    }
    brt_bvh_free(quantized);
    brt_bvh_free(decoded);
    brt_bvh_free(bvh);
    free(blob);
    tu_scene_free(&s);
}

/* A point on triangle v (barycentric a, b), moved along its normal n by
** off times its size, in float. */
static void near_point(const float v[3][3], const double n[3], float a, float b, double off,
                       float p[3])
{
    int k;
    for (k = 0; k < 3; k++)
        p[k] = (float)((1.0 - a - b) * v[0][k] + a * v[1][k] + b * v[2][k] + off * n[k]);
}

/* The early rejection of triangles behind the segment (bvh.c, "behind
** the segment") never changes an answer: brt_intersect_triangle with it
** on and off, bit for bit, on rays leaving points on, just off and just
** behind random triangles (the bounce ray's case: its own triangle just
** behind its origin), grazing and steep, with tnear 0 and a hair either
** side, at scales from 1e-3 to 1e4 and offsets up to 1e4.  Rays from
** points on the plane put t* within rounding of tnear = 0: a bound too
** tight would drop their hits. */
static void test_behind_segment(void)
{
    static const double offsets[] = {0.0, 1e-9, -1e-9, 1e-7, -1e-7, 1e-5, -1e-5, 1e-3, -1e-3};
    uint64_t st = test_seed() ^ 47;
    unsigned long cases = 0, hits = 0, near_hits = 0;
    int i;
    for (i = 0; i < 60000 && !test_failed(); i++) {
        const double scale = pow(10.0, -3.0 + 7.0 * brt_random_float(&st));
        const double shift = brt_random_u64(&st) % 2 ? 0.0 : scale * pow(10.0, 4.0 * brt_random_float(&st));
        float v[3][3];
        double e1[3], e2[3], n[3], len;
        size_t o;
        int k, j;
        for (j = 0; j < 3; j++)
            for (k = 0; k < 3; k++) v[j][k] = (float)(shift + scale * (2.0 * brt_random_float(&st) - 1.0));
        for (k = 0; k < 3; k++) {
            e1[k] = (double)v[1][k] - v[0][k];
            e2[k] = (double)v[2][k] - v[0][k];
        }
        n[0] = e1[1] * e2[2] - e1[2] * e2[1];
        n[1] = e1[2] * e2[0] - e1[0] * e2[2];
        n[2] = e1[0] * e2[1] - e1[1] * e2[0];
        len = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
        if (!(len > 0)) continue;
        for (k = 0; k < 3; k++) n[k] *= scale / len;
        for (o = 0; o < sizeof offsets / sizeof *offsets; o++) {
            const float a = brt_random_float(&st), b = (1.0f - a) * brt_random_float(&st);
            const double grazing = brt_random_u64(&st) % 4 == 0 ? 1e-6 : 1.0;
            brt_ray r;
            float t[2], u[2], vv[2];
            int hit[2], side;
            near_point((const float (*)[3])v, n, a, b, offsets[o], r.org);
            for (k = 0; k < 3; k++)
                r.dir[k] = (float)(grazing * (2.0 * brt_random_float(&st) - 1.0) * n[k] / scale +
                                   (2.0 * brt_random_float(&st) - 1.0));
            side = (int)(brt_random_u64(&st) % 3);
            r.tnear = side == 0 ? 0.0f : (side == 1 ? 1e-7f : -1e-7f);
            r.tfar = INFINITY;
            for (k = 0; k < 2; k++) {
                brt_test_early_reject(k == 0);
                t[k] = u[k] = vv[k] = 0.0f;
                hit[k] = brt_intersect_triangle(&r, v[0], v[1], v[2], &t[k], &u[k], &vv[k]);
            }
            cases++;
            hits += (unsigned long)hit[1];
            near_hits += (unsigned long)(hit[1] && fabsf(t[1] - r.tnear) <= 1e-4f * (float)scale);
            EXPECT(hit[0] == hit[1] && memcmp(t, t + 1, sizeof *t) == 0 && memcmp(u, u + 1, sizeof *u) == 0 &&
                   memcmp(vv, vv + 1, sizeof *vv) == 0,
                   "triangle %d, offset %g: early rejection %d t %a, without %d t %a", i, offsets[o],
                   hit[0], t[0], hit[1], t[1]);
        }
    }
    /* Directions of subnormal components (1/det may overflow), and
    ** triangles so small that the sheared coordinates' products and det are
    ** subnormal, with tnear a hair either side of the hit's t: the bound's
    ** underflow terms and guards. */
    for (i = 0; i < 60000 && !test_failed(); i++) {
        float v[3][3], t[2], u[2], vv[2], t0 = 0, u0, v0;
        brt_ray r;
        int hit[2], j, k;
        const int size = i % 2 ? 0 : -55 - (int)(brt_random_u64(&st) % 20);   /* or tiny triangles */
        for (j = 0; j < 3; j++)
            for (k = 0; k < 3; k++) v[j][k] = (float)ldexp(2.0 * brt_random_float(&st) - 1.0, size);
        for (k = 0; k < 3; k++) {
            r.org[k] = (float)ldexp(2.0 * brt_random_float(&st) - 1.0, size);
            r.dir[k] = (float)ldexp(2.0 * brt_random_float(&st) - 1.0,
                                    i % 4 == 1 ? 0 : -100 - (int)(brt_random_u64(&st) % 50));
        }
        if (brt_random_u64(&st) % 2) r.dir[brt_random_u64(&st) % 3] = 0.0f;
        r.tnear = -INFINITY;
        r.tfar = INFINITY;
        brt_test_early_reject(0);
        if (!brt_intersect_triangle(&r, v[0], v[1], v[2], &t0, &u0, &v0) || !isfinite(t0)) continue;
        r.tnear = brt_random_u64(&st) % 2 ? nextafterf(t0, -INFINITY) : t0 * (1.0f + 0x1p-20f);
        for (k = 0; k < 2; k++) {
            brt_test_early_reject(k == 0);
            t[k] = u[k] = vv[k] = 0.0f;
            hit[k] = brt_intersect_triangle(&r, v[0], v[1], v[2], &t[k], &u[k], &vv[k]);
        }
        cases++;
        EXPECT(hit[0] == hit[1] && memcmp(t, t + 1, sizeof *t) == 0,
               "subnormal direction (%a %a %a), tnear %a: early rejection %d t %a, without %d t %a", r.dir[0],
               r.dir[1], r.dir[2], r.tnear, hit[0], t[0], hit[1], t[1]);
    }
    brt_test_early_reject(1);
    printf("  bvh: behind the segment: %lu rays, %lu hits, %lu of them at tnear within 1e-4 of the size\n",
           cases, hits, near_hits);
    EXPECT(near_hits > 1000, "only %lu hits at tnear: the cases miss the bound's edge", near_hits);
}

static void test_blob(void)
{
    uint64_t st = test_seed() ^ 41;
    tu_scene s = {0};
    brt_bvh *bvh, *opened = NULL;
    brt_error err;
    unsigned char *blob, *bad;
    size_t size, n, i;
    float lo[3], hi[3];
    tu_random_soup(&s, &st, 2000, 0.05f);
    bvh = build_checked(&s, NULL);
    if (!bvh) { tu_scene_free(&s); return; }
    size = brt_bvh_blob_size(bvh);
    blob = malloc(size);
    bad = malloc(size);
    brt_bvh_blob_write(bvh, blob);
    CHECK(brt_bvh_blob_open(blob, size, s.tcount, &opened, &err) == BRT_OK, "open: %s", err.message);
    CHECK(brt_bvh_check(opened, &err) == BRT_OK, "check opened: %s", err.message);
    tu_scene_bounds(&s, lo, hi);
    for (n = 0; n < 1000 && !test_failed(); n++) {
        brt_ray r;
        brt_hit a, b;
        tu_make_ray(&s, lo, hi, (int)(n % TU_RAY_KINDS), &st, &r);
        brt_hit_clear(&a);
        brt_hit_clear(&b);
        brt_bvh_intersect(bvh, &r, &a);
        brt_bvh_intersect(opened, &r, &b);
        EXPECT(memcmp(&a, &b, sizeof a) == 0, "ray %zu: opened blob differs", n);
    }
    brt_bvh_free(opened);

    expect_eformat(blob, size - 1, "truncated by one byte");
    expect_eformat(blob, size - 10, "one triangle short");
    expect_eformat(blob, 8, "shorter than a header");
    memcpy(bad, blob, size); put_u32(bad, 0, 0x12345678u);
    expect_eformat(bad, size, "bad magic");
    memcpy(bad, blob, size); put_u32(bad, 4, get_u32(blob, 4) + 1);
    expect_eformat(bad, size, "node count one too many");
    memcpy(bad, blob, size); put_u32(bad, 12, 0xFFFFFFF0u);
    expect_eformat(bad, size, "huge triangle count");
    memcpy(bad, blob, size); put_u32(bad, 60, 1);
    expect_eformat(bad, size, "nonzero header padding");
    /* the root's slot 0 made inner, its children's first index moved */
    memcpy(bad, blob, size); bad[HEADER_BYTES + COUNT] = 0;
    put_u32(bad, HEADER_BYTES + FIRST_NODE, 1000000u);
    expect_eformat(bad, size, "child node out of range");
    memcpy(bad, blob, size); bad[HEADER_BYTES + COUNT] = 0;
    put_u32(bad, HEADER_BYTES + FIRST_NODE, 0);
    expect_eformat(bad, size, "child pointing at the root (a cycle)");
    memcpy(bad, blob, size); bad[HEADER_BYTES + COUNT] = 3;
    put_u32(bad, HEADER_BYTES + FIRST_TRI, s.tcount - 1);
    expect_eformat_saying(bad, size, "leaf range past the end", "bad leaf range");
    memcpy(bad, blob, size); bad[HEADER_BYTES + COUNT] = MAX_LEAF + 1;
    expect_eformat(bad, size, "a leaf of more than MAX_LEAF triangles");
    {   /* the vertex base of the first node with a leaf, past the vertices */
        size_t at = HEADER_BYTES;
        while (!node_has_leaf(blob + at)) at += NODE_BYTES;
        memcpy(bad, blob, size); put_u32(bad, at + VERTEX_BASE, get_u32(blob, 8));
        expect_eformat(bad, size, "vertex base past the vertices");
    }
    {   /* the last corner offset of the last triangle past the vertices */
        const size_t last = size - 2;
        const uint16_t big = 0xFFFF;
        memcpy(bad, blob, size); memcpy(bad + last, &big, 2);
        expect_eformat(bad, size, "corner offset past the vertices");
    }
    {   /* a leaf slot made inner, its triangles merged into the next leaf
        ** slot (which then starts where it did): slots still ordered, every
        ** triangle in one leaf, no node orphaned, but the new inner slot
        ** takes the node after its parent's children, which has a parent */
        const uint32_t nodes = get_u32(blob, 4);
        uint32_t node, slot, found = 0;
        for (node = 0; node < nodes && !found; node++) {
            unsigned char *c = blob + HEADER_BYTES + NODE_BYTES * (size_t)node + COUNT;
            for (slot = 0; slot + 1 < 4 && !found; slot++) {
                if ((slot > 0 && c[slot - 1] != 0) || c[slot] == 0 || c[slot] > MAX_LEAF ||
                    c[slot + 1] == 0 || c[slot + 1] > MAX_LEAF || c[slot] + c[slot + 1] > MAX_LEAF ||
                    get_u32(blob, HEADER_BYTES + NODE_BYTES * (size_t)node + FIRST_NODE) + slot >= nodes)
                    continue;
                memcpy(bad, blob, size);
                bad[c - blob + slot + 1] = (unsigned char)(c[slot] + c[slot + 1]);
                bad[c - blob + slot] = 0;
                expect_eformat(bad, size, "a node with two parents");
                found = 1;
            }
        }
        EXPECT(found, "no pair of leaf slots in the test BVH to damage");
    }
    {   /* an inner slot and the leaf after it swapped: every index the
        ** slots reach is still fine, only their order is wrong (traversal
        ** finds an inner slot's child by its position) */
        const uint32_t nodes = get_u32(blob, 4);
        uint32_t node, slot, found = 0;
        for (node = 0; node < nodes && !found; node++) {
            unsigned char *c = blob + HEADER_BYTES + NODE_BYTES * (size_t)node + COUNT;
            for (slot = 0; slot + 1 < 4 && !found; slot++) {
                if (c[slot] != 0 || c[slot + 1] == 0 || c[slot + 1] > MAX_LEAF) continue;
                memcpy(bad, blob, size);
                bad[c - blob + slot] = c[slot + 1];
                bad[c - blob + slot + 1] = 0;
                expect_eformat(bad, size, "an inner slot after a leaf");
                found = 1;
            }
        }
        EXPECT(found, "no inner slot before a leaf in the test BVH");
    }
    {   /* an empty slot made inner: slots out of order */
        const uint32_t nodes = get_u32(blob, 4);
        uint32_t node, slot, found = 0;
        for (node = 0; node < nodes && !found; node++)
            for (slot = 0; slot < 4 && !found; slot++) {
                const size_t at = HEADER_BYTES + NODE_BYTES * (size_t)node + COUNT + slot;
                if (blob[at] != 0xFF) continue;
                memcpy(bad, blob, size);
                bad[at] = 0;
                expect_eformat(bad, size, "an empty slot made inner");
                found = 1;
            }
        EXPECT(found, "no empty slot in the test BVH to damage");
    }
    /* Random damage to the nodes' boxes, child and triangle indices and
    ** counts (not the vertex base, which would change the triangles): a
    ** format error, or a BVH whose structure holds (open checks it) and
    ** which, since vertices and prims are intact, reports only real hits:
    ** the triangle's own t, u, v, never closer than brute force. */
    for (i = 0; i < 300 && !test_failed(); i++) {
        const size_t nodes = get_u32(blob, 4);
        size_t at = HEADER_BYTES + NODE_BYTES * (brt_random_u64(&st) % nodes)
                    + 24 + brt_random_u64(&st) % 36;
        brt_result r;
        if (at % NODE_BYTES >= VERTEX_BASE) at += 4;   /* skip vertex_base */
        memcpy(bad, blob, size);
        bad[at] = (unsigned char)brt_random_u64(&st);
        r = brt_bvh_blob_open(bad, size, s.tcount, &opened, &err);
        EXPECT(r == BRT_OK || r == BRT_EFORMAT, "damaged byte %zu: %s", at, brt_result_string(r));
        if (r == BRT_OK) {
            int k;
            for (k = 0; k < 10 && !test_failed(); k++) {
                brt_ray ray;
                brt_hit h, want;
                float t, u, v;
                tu_make_ray(&s, lo, hi, k & 1 ? TU_RANDOM : TU_CAMERA, &st, &ray);
                brt_hit_clear(&h);
                brt_hit_clear(&want);
                brt_bvh_intersect(opened, &ray, &h);
                tu_brute_force(&s, NULL, &ray, &want);
                if (h.prim == BRT_NO_PRIM) continue;
                EXPECT(h.prim < s.tcount &&
                       brt_intersect_triangle(&ray, tu_vertex(&s, h.prim, 0), tu_vertex(&s, h.prim, 1),
                                              tu_vertex(&s, h.prim, 2), &t, &u, &v) &&
                       t == h.t && u == h.u && v == h.v && !brt_hit_is_closer(h.t, h.inst, h.prim, &want),
                       "damaged byte %zu: hit t=%a prim %u is not a hit of that triangle, or beats "
                       "brute force (t=%a prim %u)", at, h.t, (unsigned)h.prim, want.t, (unsigned)want.prim);
            }
            brt_bvh_free(opened);
        }
    }
    free(bad);
    free(blob);
    brt_bvh_free(bvh);
    tu_scene_free(&s);
}

static void test_bounds_and_memory(void)
{
    uint64_t st = test_seed() ^ 43;
    tu_scene s = {0};
    brt_bvh *bvh;
    float lo[3], hi[3], blo[3], bhi[3];
    int a;
    tu_random_soup(&s, &st, 100, 0.1f);
    bvh = build_checked(&s, NULL);
    if (!bvh) { tu_scene_free(&s); return; }
    tu_scene_bounds(&s, lo, hi);
    brt_bvh_bounds(bvh, blo, bhi);
    for (a = 0; a < 3; a++)
        EXPECT(blo[a] <= lo[a] && bhi[a] >= hi[a] && hi[a] - bhi[a] > -1e-4f && blo[a] - lo[a] > -1e-4f,
               "axis %d: bvh bounds [%g,%g] vs mesh [%g,%g]", a, blo[a], bhi[a], lo[a], hi[a]);
    EXPECT(brt_bvh_memory_bytes(bvh) >= 36u * s.tcount, "memory bytes %zu", brt_bvh_memory_bytes(bvh));
    brt_bvh_free(bvh);
    tu_scene_free(&s);
}

void suite_bvh(void)
{
    test_run("bvh: triangle exact values", test_triangle_exact);
    test_run("bvh: 4-wide box test == one-box test", test_box_span4);
    test_run("bvh: double-precision fallback", test_double_fallback);
    test_run("bvh: edge rays == exact orientation", test_edge_rays);
    test_run("bvh: degenerate triangles never hit", test_degenerate_triangles);
    test_run("bvh: a box entered at the closest hit is visited", test_entry_equals_hit);
    test_run("bvh: random soups == brute force", test_random_soups);
    test_run("bvh: prim ids == brute force", test_prim_ids);
    test_run("bvh: more than 65536 corners (16-bit offsets) == brute force", test_vertex_window);
    test_run("bvh: coplanar == brute force", test_coplanar);
    test_run("bvh: axis grid == brute force", test_axis_grid);
    test_run("bvh: duplicates == brute force", test_duplicates);
    test_run("bvh: slivers, zero area == brute force", test_slivers_and_zero_area);
    test_run("bvh: grazing rays: exact, inside the box span, accurate t", test_grazing);
    test_run("bvh: tiny and huge scales == brute force", test_scales);
    test_run("bvh: bunny_tiny == brute force", test_mesh_bunny_tiny);
    test_run("bvh: bunny == brute force", test_mesh_bunny);
    test_run("bvh: dragon == brute force", test_mesh_dragon);
    test_run("bvh: bmw_m6 == brute force", test_mesh_bmw);
    test_run("bvh: crown == brute force", test_mesh_crown);
    test_run("bvh: fg_oahu == brute force", test_mesh_oahu);
    test_run("bvh: watertight icosphere", test_watertight_icosphere);
    test_run("bvh: watertight cube grid", test_watertight_cubes);
    test_run("bvh: watertight from far away", test_watertight_far);
    test_run("bvh: degenerate rays miss", test_degenerate_rays);
    test_run("bvh: non-finite vertices rejected", test_nonfinite_vertices);
    test_run("bvh: empty", test_empty);
    test_run("bvh: blob round trip and corruption", test_blob);
    test_run("bvh: behind the segment, rejected early with the same answers", test_behind_segment);
    test_run("bvh: a decoded blob and the prepared walk answer as the blob", test_decoded_and_prepared);
    test_run("bvh: bounds and memory", test_bounds_and_memory);
    test_run("bvh: resident layout checker rejects every flipped bit", test_resident_check);
}
