/*
** tests/test_instances.c -- instancing in direct mode (issue 28, parts 1
** and 3): a brt_world against brute force "evaluated with the same
** transform of the ray" (tu_instanced_brute: every instance, every
** triangle, the ray carried into object space by brt_instance_ray) on
** adversarial transforms; the tie-break by (t, inst, prim); world normals;
** the checks of instances at build; instanced hit files.
*/
#include "test.h"
#include "util.h"
#include "../examples/lib/referee.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <sys/resource.h>
#include <sys/wait.h>

static void identity(float m[12])
{
    memset(m, 0, 12 * sizeof *m);
    m[0] = m[5] = m[10] = 1.0f;
}

/* m = (rotation by angle about a unit axis) * diag(s), then translated. */
static void rotation(float m[12], const float axis[3], float angle, const float s[3],
                     const float t[3])
{
    const float c = cosf(angle), n = sinf(angle), k = 1.0f - c;
    const float x = axis[0], y = axis[1], z = axis[2];
    const float r[9] = {c + x * x * k, x * y * k - z * n, x * z * k + y * n,
                        y * x * k + z * n, c + y * y * k, y * z * k - x * n,
                        z * x * k - y * n, z * y * k + x * n, c + z * z * k};
    int i, j;
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++) m[4 * i + j] = r[3 * i + j] * s[j];
        m[4 * i + 3] = t[i];
    }
}

/* The adversarial scene: a world soup, three prototypes (a soup, a
** closed box, one small triangle) and instances under every kind of
** transform the issue names.  Returns the number of "kinds" placed. */
static void adversarial_scene(tu_instanced *s, uint64_t *st)
{
    float m[12];
    uint32_t i;
    memset(s, 0, sizeof *s);
    tu_random_soup(&s->world, st, 200, 0.1f);
    s->proto_count = 3;
    tu_random_soup(&s->protos[0], st, 300, 0.15f);
    {   /* a closed unit cube: shared edges, watertightness across them */
        static const float v[8][3] = {{0,0,0},{1,0,0},{1,1,0},{0,1,0},{0,0,1},{1,0,1},{1,1,1},{0,1,1}};
        static const uint32_t f[12][3] = {{0,2,1},{0,3,2},{4,5,6},{4,6,7},{0,1,5},{0,5,4},
                                          {1,2,6},{1,6,5},{2,3,7},{2,7,6},{3,0,4},{3,4,7}};
        for (i = 0; i < 8; i++) tu_add_vertex(&s->protos[1], v[i][0], v[i][1], v[i][2]);
        for (i = 0; i < 12; i++) tu_add_triangle(&s->protos[1], f[i][0], f[i][1], f[i][2]);
    }
    tu_add_vertex(&s->protos[2], 0, 0, 0);
    tu_add_vertex(&s->protos[2], 1, 0, 0);
    tu_add_vertex(&s->protos[2], 0, 1, 0.25f);
    tu_add_triangle(&s->protos[2], 0, 1, 2);
    /* 0: identity over the world's own cube: ties with world triangles? no
    ** (different triangles), but shares its space. */
    identity(m);
    tu_add_instance(s, 0, m);
    /* 1: a translation of 1e6 */
    identity(m);
    m[3] = 1e6f; m[7] = -1e6f; m[11] = 5e5f;
    tu_add_instance(s, 0, m);
    /* 2, 3: scales 1e-3 and 1e3 (the first thinner than any voxel) */
    {
        const float ax[3] = {0, 0, 1}, s1[3] = {1e-3f, 1e-3f, 1e-3f}, s2[3] = {1e3f, 1e3f, 1e3f};
        const float t1[3] = {0.5f, 0.5f, 0.5f}, t2[3] = {3e3f, 0, 0};
        rotation(m, ax, 0.3f, s1, t1);
        tu_add_instance(s, 1, m);
        rotation(m, ax, 1.1f, s2, t2);
        tu_add_instance(s, 0, m);
    }
    /* 4: a rotation; 5: a mirror (negative determinant); 6: a shear */
    {
        const float ax[3] = {0.48f, 0.6f, 0.64f}, one[3] = {1, 1, 1}, t[3] = {2, 0, 0};
        const float mirror[3] = {-1, 1, 1}, t5[3] = {4, 0, 0};
        rotation(m, ax, 2.0f, one, t);
        tu_add_instance(s, 1, m);
        rotation(m, ax, 0.7f, mirror, t5);
        tu_add_instance(s, 0, m);
        identity(m);
        m[1] = 0.5f; m[6] = 0.3f; m[2] = -0.2f; m[3] = 6;
        tu_add_instance(s, 1, m);
    }
    /* 7: condition number near the bound (a flat scale of 1000:1) */
    identity(m);
    m[10] = 1e-3f; m[3] = 8;
    tu_add_instance(s, 0, m);
    /* 8..27: many instances of one prototype in one place, the first ten
    ** identical (exact ties: the lowest instance must win), then small
    ** rotations of it */
    for (i = 0; i < 20; i++) {
        const float ax[3] = {0, 1, 0}, one[3] = {1, 1, 1}, t[3] = {10, 0, 0};
        rotation(m, ax, i < 10 ? 0.0f : 0.01f * (float)i, one, t);
        tu_add_instance(s, i % 2 ? 1 : 2, m);
    }
}

/* A ray at instance k (or at the world when k == instance_count): from a
** random point a few box sizes away (sometimes a thousand) towards a
** random point of one of its triangles, a tenth of them on an edge. */
static void ray_at(const tu_instanced *s, uint32_t k, uint64_t *st, brt_ray *r)
{
    const tu_scene *mesh = k < s->instance_count ? &s->protos[s->instances[k].prototype] : &s->world;
    const uint32_t tri = (uint32_t)(brt_random_u64(st) % mesh->tcount);
    float u = brt_random_float(st), v = brt_random_float(st), p[3], w[3], d[3];
    float span = 1.0f;
    int a;
    if (u + v > 1.0f) { u = 1.0f - u; v = 1.0f - v; }
    if (brt_random_float(st) < 0.1f) v = 0.0f;   /* on an edge: watertightness */
    for (a = 0; a < 3; a++)
        p[a] = (1 - u - v) * tu_vertex(mesh, tri, 0)[a] + u * tu_vertex(mesh, tri, 1)[a] +
               v * tu_vertex(mesh, tri, 2)[a];
    if (k < s->instance_count) {
        const float *x = s->instances[k].xform;
        for (a = 0; a < 3; a++) w[a] = x[4 * a] * p[0] + x[4 * a + 1] * p[1] + x[4 * a + 2] * p[2] + x[4 * a + 3];
        span = fabsf(x[0]) + fabsf(x[1]) + fabsf(x[2]) + fabsf(x[5]) + fabsf(x[10]);
    } else {
        memcpy(w, p, sizeof w);
    }
    tu_random_unit(st, d);
    if (brt_random_float(st) < 0.2f) span *= 1000.0f;
    for (a = 0; a < 3; a++) {
        r->org[a] = w[a] + span * (1.0f + 3.0f * brt_random_float(st)) * d[a];
        r->dir[a] = w[a] - r->org[a];
    }
    r->tnear = 0.0f;
    r->tfar = brt_random_float(st) < 0.1f ? 0.9f : INFINITY;
}

static int same_hit(const brt_hit *a, const brt_hit *b)
{
    return memcmp(a, b, sizeof *a) == 0;
}

static void test_direct_equals_brute_force(void)
{
    tu_instanced s;
    brt_scene_source src;
    brt_world *w = NULL;
    brt_error err;
    uint64_t st = test_seed() + 2801;
    uint32_t k, on_instances = 0, ties = 0, n = 0, bad = 0;
    adversarial_scene(&s, &st);
    tu_instanced_source(&s, &src);
    CHECK(brt_world_build(&src, &w, &err) == BRT_OK, "%s", err.message);
    EXPECT(brt_world_instance_count(w) == s.instance_count && brt_world_prototype_count(w) == 3,
           "counts");
    for (k = 0; k <= s.instance_count; k++) {
        int i;
        for (i = 0; i < 80; i++, n++) {
            brt_ray r;
            brt_hit want, got;
            ray_at(&s, k, &st, &r);
            brt_hit_clear(&want);
            brt_hit_clear(&got);
            tu_instanced_brute(&s, &r, &want);
            brt_world_intersect(w, &r, &got, NULL);
            if (!same_hit(&want, &got) && bad++ < 5)
                test_fail_at(__FILE__, __LINE__,
                             "instance %u ray %d: world t=%a inst %u prim %u, brute force t=%a inst %u prim %u",
                             (unsigned)k, i, got.t, (unsigned)got.inst, (unsigned)got.prim, want.t,
                             (unsigned)want.inst, (unsigned)want.prim);
            on_instances += want.inst != BRT_NO_INST;
            ties += k >= 8 && k < 18 && want.inst == 8u + k % 2u;
            EXPECT(brt_world_occluded(w, &r) == tu_instanced_brute_occluded(&s, &r),
                   "instance %u ray %d: occlusion differs", (unsigned)k, i);
        }
    }
    EXPECT(on_instances > n / 2, "only %u of %u rays hit an instance", (unsigned)on_instances, (unsigned)n);
    EXPECT(ties > 100, "only %u rays at the identical instances were won by the lowest", (unsigned)ties);
    brt_world_free(w);
    tu_instanced_free(&s);
}

/* brt_world_trace over threads writes what brt_world_intersect does. */
static void test_trace_threads(void)
{
    enum { N = 3000 };
    tu_instanced s;
    brt_scene_source src;
    brt_world *w = NULL;
    brt_error err;
    uint64_t st = test_seed() + 2802;
    brt_ray *rays = malloc(N * sizeof *rays);
    brt_hit *one = malloc(N * sizeof *one), *two = malloc(N * sizeof *two), h;
    float *n1 = malloc(3 * N * sizeof *n1), *n2 = malloc(3 * N * sizeof *n2);
    size_t i;
    CHECK(rays && one && two && n1 && n2, "out of memory");
    adversarial_scene(&s, &st);
    tu_instanced_source(&s, &src);
    CHECK(brt_world_build(&src, &w, &err) == BRT_OK, "%s", err.message);
    for (i = 0; i < N; i++) ray_at(&s, (uint32_t)(i % (s.instance_count + 1)), &st, &rays[i]);
    brt_world_trace(w, rays, NULL, N, one, n1, 1);
    brt_world_trace(w, rays, NULL, N, two, n2, 7);
    EXPECT(memcmp(one, two, N * sizeof *one) == 0 && memcmp(n1, n2, 3 * N * sizeof *n1) == 0,
           "1 and 7 threads differ");
    for (i = 0; i < N; i++) {
        brt_hit_clear(&h);
        brt_world_intersect(w, &rays[i], &h, NULL);
        if (!same_hit(&h, &one[i])) {
            test_fail_at(__FILE__, __LINE__, "ray %zu: trace differs from intersect", i);
            break;
        }
    }
    brt_world_free(w);
    tu_instanced_free(&s);
    free(rays); free(one); free(two); free(n1); free(n2);
}

/* An instance's normal is its world triangle's (v1-v0) x (v2-v0): the
** cross product of the transformed corners, in double, points the same
** way (a mirror flips the winding, and the normal with it). */
static void test_world_normals(void)
{
    tu_instanced s;
    brt_scene_source src;
    brt_world *w = NULL;
    brt_error err;
    uint64_t st = test_seed() + 2803;
    uint32_t k, checked = 0;
    adversarial_scene(&s, &st);
    tu_instanced_source(&s, &src);
    CHECK(brt_world_build(&src, &w, &err) == BRT_OK, "%s", err.message);
    for (k = 0; k < 8; k++) {
        int i;
        for (i = 0; i < 20; i++) {
            brt_ray r;
            brt_hit h;
            float n[3];
            double c[3][3], e1[3], e2[3], x[3], dot = 0, nn = 0, xx = 0;
            int a, j;
            ray_at(&s, k, &st, &r);
            brt_hit_clear(&h);
            brt_world_intersect(w, &r, &h, n);
            if (h.inst != k) continue;
            for (j = 0; j < 3; j++) {
                const float *v = tu_vertex(&s.protos[s.instances[k].prototype], h.prim, j);
                const float *m = s.instances[k].xform;
                for (a = 0; a < 3; a++)
                    c[j][a] = (double)m[4 * a] * v[0] + (double)m[4 * a + 1] * v[1] + (double)m[4 * a + 2] * v[2];
            }
            for (a = 0; a < 3; a++) { e1[a] = c[1][a] - c[0][a]; e2[a] = c[2][a] - c[0][a]; }
            x[0] = e1[1] * e2[2] - e1[2] * e2[1];
            x[1] = e1[2] * e2[0] - e1[0] * e2[2];
            x[2] = e1[0] * e2[1] - e1[1] * e2[0];
            for (a = 0; a < 3; a++) { dot += x[a] * n[a]; nn += (double)n[a] * n[a]; xx += x[a] * x[a]; }
            EXPECT(dot > 0.999 * sqrt(nn * xx), "instance %u prim %u: normal off the world triangle's",
                   (unsigned)k, (unsigned)h.prim);
            checked++;
        }
    }
    EXPECT(checked > 40, "only %u normals checked", (unsigned)checked);
    brt_world_free(w);
    tu_instanced_free(&s);
}

/* At equal t the instance beats the world triangle, and the lower
** instance the higher: a world triangle and two instances of the same
** triangle under the identity all meet the ray at the same t. */
static void test_tie_break(void)
{
    tu_instanced s;
    brt_scene_source src;
    brt_world *w = NULL;
    brt_error err;
    brt_hit h;
    float m[12];
    const brt_ray r = {{0.25f, 0.25f, 1}, {0, 0, -1}, 0, INFINITY};
    memset(&s, 0, sizeof s);
    tu_add_vertex(&s.world, 0, 0, 0);
    tu_add_vertex(&s.world, 1, 0, 0);
    tu_add_vertex(&s.world, 0, 1, 0);
    tu_add_triangle(&s.world, 0, 1, 2);
    s.proto_count = 1;
    tu_add_vertex(&s.protos[0], 0, 0, 0);
    tu_add_vertex(&s.protos[0], 1, 0, 0);
    tu_add_vertex(&s.protos[0], 0, 1, 0);
    tu_add_triangle(&s.protos[0], 0, 1, 2);
    identity(m);
    tu_add_instance(&s, 0, m);
    tu_add_instance(&s, 0, m);
    tu_instanced_source(&s, &src);
    CHECK(brt_world_build(&src, &w, &err) == BRT_OK, "%s", err.message);
    brt_hit_clear(&h);
    brt_world_intersect(w, &r, &h, NULL);
    EXPECT(h.t == 1.0f && h.inst == 0 && h.prim == 0, "t=%g inst %u prim %u: instance 0 should win",
           h.t, (unsigned)h.inst, (unsigned)h.prim);
    brt_world_free(w);
    s.instance_count = 0;   /* the world triangle alone */
    tu_instanced_source(&s, &src);
    CHECK(brt_world_build(&src, &w, &err) == BRT_OK, "%s", err.message);
    brt_hit_clear(&h);
    brt_world_intersect(w, &r, &h, NULL);
    EXPECT(h.t == 1.0f && h.inst == BRT_NO_INST && h.prim == 0, "world triangle: inst %u",
           (unsigned)h.inst);
    brt_world_free(w);
    tu_instanced_free(&s);
}

static brt_scene *build_instanced(const tu_instanced *s, uint32_t point_tris, const char *name);

/* The world normal of instance k's triangle prim: (v1-v0) x (v2-v0) of
** the corners carried by its xform in double (not the library's cofactor). */
static void world_normal_of(const tu_instanced *s, uint32_t k, uint32_t prim, double x[3])
{
    double c[3][3], e1[3], e2[3];
    int a, j;
    for (j = 0; j < 3; j++) {
        const float *v = tu_vertex(&s->protos[s->instances[k].prototype], prim, j);
        const float *m = s->instances[k].xform;
        for (a = 0; a < 3; a++)
            c[j][a] = (double)m[4 * a] * v[0] + (double)m[4 * a + 1] * v[1] + (double)m[4 * a + 2] * v[2] +
                      m[4 * a + 3];
    }
    for (a = 0; a < 3; a++) { e1[a] = c[1][a] - c[0][a]; e2[a] = c[2][a] - c[0][a]; }
    x[0] = e1[1] * e2[2] - e1[2] * e2[1];
    x[1] = e1[2] * e2[0] - e1[0] * e2[2];
    x[2] = e1[0] * e2[1] - e1[1] * e2[0];
}

/* Whether n points along instance k's triangle prim's world normal. */
static int normal_is_of(const tu_instanced *s, uint32_t k, uint32_t prim, const float n[3])
{
    double x[3], dot = 0, nn = 0, xx = 0;
    int a;
    if (k >= s->instance_count) return 0;
    world_normal_of(s, k, prim, x);
    for (a = 0; a < 3; a++) { dot += x[a] * n[a]; nn += (double)n[a] * n[a]; xx += x[a] * x[a]; }
    return xx > 0 && dot > 0.999 * sqrt(nn * xx);
}

typedef struct normal_sink {    /* the finished calls of a stream of rays */
    const brt_ray *rays;
    size_t count, next;
    brt_hit hits[16];
    float normals[16][3];
} normal_sink;

static size_t sink_next(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    normal_sink *k = user;
    size_t n = 0;
    while (n < max && k->next < k->count) {
        rays[n] = k->rays[k->next];
        tags[n++] = k->next++;
    }
    return n;
}

static void sink_finished(void *user, const brt_ray *ray, const brt_hit *hit, const float normal[3],
                          uint32_t visits, uint64_t tag)
{
    normal_sink *k = user;
    (void)ray; (void)visits;
    if (tag < 16) { k->hits[tag] = *hit; memcpy(k->normals[tag], normal, sizeof k->normals[tag]); }
}

/* README, "Hits": "among hits at the same smallest t the lowest (inst,
** prim) wins", and the normal is the hit triangle's (brt_bvh_intersect_
** normal: "whenever the hit changes, normal becomes the geometric normal
** of the new hit's triangle").  One triangle symmetric about x = 0 under
** two transforms that map it onto itself, the identity and a turn of 180
** degrees about y (which flips its normal): every ray meets both at the
** same t, and the tie goes to the lower instance with a different normal
** and other (u, v).  The winner's normal must come with it whichever
** instance is tested first: the instance function called in both orders,
** the world (instances in either numbering) and the batched stream; each
** checked against the corners carried by the xform in double. */
static void test_tie_carries_normal(void)
{
    static const brt_ray rays[4] = {{{0.1f, -0.2f, 1}, {0, 0, -1}, 0, INFINITY},
                                    {{-0.3f, 0.1f, -2}, {0, 0, 1}, 0, INFINITY},
                                    {{0.05f, 0.4f, 3}, {0.01f, -0.02f, -1}, 0, INFINITY},
                                    {{-0.2f, -0.5f, 1}, {0, 0, -0.5f}, 0, INFINITY}};
    float turn[12] = {-1, 0, 0, 0, 0, 1, 0, 0, 0, 0, -1, 0}, ident[12];
    int order;
    identity(ident);
    for (order = 0; order < 4; order++) {      /* bit 0: which instance turns; bit 1: one prototype */
        tu_instanced s;
        brt_scene_source src;
        brt_world *w = NULL;
        brt_bvh *proto[2] = {NULL, NULL};
        brt_instance_frame frame[2];
        brt_scene *scene;
        brt_error err;
        normal_sink sink;
        brt_ray_source source;
        brt_trace_options opt;
        uint32_t i, k;
        memset(&s, 0, sizeof s);
        s.proto_count = 2;      /* 0: a triangle far off, then the symmetric one (prim 1); 1: that one alone */
        tu_add_vertex(&s.protos[0], 50, 50, 50);
        tu_add_vertex(&s.protos[0], 51, 50, 50);
        tu_add_vertex(&s.protos[0], 50, 51, 50);
        tu_add_triangle(&s.protos[0], 0, 1, 2);
        for (k = 0; k < 2; k++) {
            const uint32_t b = s.protos[k].vcount;
            tu_add_vertex(&s.protos[k], -1, -1, 0);
            tu_add_vertex(&s.protos[k], 1, -1, 0);
            tu_add_vertex(&s.protos[k], 0, 1, 0);
            tu_add_triangle(&s.protos[k], b, b + 1, b + 2);
        }
        /* instance 0 wins by its number with prim 1 over instance 1's prim 0 */
        tu_add_instance(&s, 0, order & 1 ? turn : ident);
        tu_add_instance(&s, order >> 1 ? 0 : 1, order & 1 ? ident : turn);   /* same prim 1, or prim 0 */
        for (k = 0; k < 2; k++)
            CHECK(brt_bvh_build(s.protos[k].pos, s.protos[k].idx, s.protos[k].tcount, NULL, &proto[k]) == BRT_OK,
                  "prototype BVH");
        for (k = 0; k < 2; k++)
            CHECK(brt_instance_frame_init(&s.instances[k], k, &frame[k], &err) == BRT_OK, "%s", err.message);
        tu_instanced_source(&s, &src);
        CHECK(brt_world_build(&src, &w, &err) == BRT_OK, "%s", err.message);
        for (i = 0; i < 4; i++) {
            brt_hit h, want;
            float n[3];
            int first;
            brt_hit_clear(&want);
            tu_instanced_brute(&s, &rays[i], &want);
            CHECK(want.inst == 0 && want.prim == 1, "ray %u: brute force names inst %u prim %u (README: the "
                  "lowest (inst, prim) wins: inst 0 prim 1)", (unsigned)i, (unsigned)want.inst, (unsigned)want.prim);
            for (first = 0; first < 2; first++) {       /* instance 1 tested first, then 0 first */
                brt_hit_clear(&h);
                memset(n, 0, sizeof n);
                brt_instance_intersect(proto[s.instances[!first].prototype], &frame[!first], !first, &rays[i], &h, n);
                brt_instance_intersect(proto[s.instances[first].prototype], &frame[first], first, &rays[i], &h, n);
                EXPECT(memcmp(&h, &want, sizeof h) == 0 && normal_is_of(&s, 0, 1, n),
                       "order %d ray %u, instance %d first: hit inst %u t %g, normal (%g %g %g) not instance "
                       "0's", order, (unsigned)i, !first, (unsigned)h.inst, h.t, n[0], n[1], n[2]);
            }
            brt_hit_clear(&h);
            brt_world_intersect(w, &rays[i], &h, n);
            EXPECT(memcmp(&h, &want, sizeof h) == 0 && normal_is_of(&s, 0, 1, n),
                   "order %d ray %u, world: inst %u, normal (%g %g %g) not instance 0's", order, (unsigned)i,
                   (unsigned)h.inst, n[0], n[1], n[2]);
        }
        scene = build_instanced(&s, 1000, "tie-normal.brs");
        CHECK(scene, "no scene");
        memset(&sink, 0, sizeof sink);
        sink.rays = rays;
        sink.count = 4;
        source.next_rays = sink_next;
        source.finished = sink_finished;
        source.user = &sink;
        memset(&opt, 0, sizeof opt);
        opt.threads = 1;
        opt.memory_limit = order & 1 ? 0 : 1;   /* in core, and every load oversized */
        EXPECT(brt_scene_trace_stream(scene, &opt, &source, NULL, &err) == BRT_OK, "%s", err.message);
        for (i = 0; i < 4; i++)
            EXPECT(sink.hits[i].inst == 0 && sink.hits[i].prim == 1 && normal_is_of(&s, 0, 1, sink.normals[i]),
                   "order %d ray %u, batched: inst %u, normal (%g %g %g) not instance 0's", order, (unsigned)i,
                   (unsigned)sink.hits[i].inst, sink.normals[i][0], sink.normals[i][1], sink.normals[i][2]);
        brt_scene_close(scene);
        brt_world_free(w);
        brt_bvh_free(proto[0]);
        brt_bvh_free(proto[1]);
        tu_instanced_free(&s);
    }
}

/* Each check of an instance at build, by its message. */
static void test_bad_instances(void)
{
    static const struct { int entry; float value; uint32_t proto; const char *words; } cases[] = {
        {0, 0.0f, 0, "singular"},             /* with m[5], m[10] zeroed below: rank 1 */
        {3, NAN, 0, "non-finite"},
        {10, 1.0f / 2048.0f, 0, "condition number"},
        {-1, 0, 5, "prototype 5 out of range"},
    };
    size_t c;
    for (c = 0; c < sizeof cases / sizeof cases[0]; c++) {
        tu_instanced s;
        brt_scene_source src;
        brt_world *w = (brt_world *)&s;
        brt_error err;
        float m[12];
        memset(&s, 0, sizeof s);
        s.proto_count = 1;
        tu_add_vertex(&s.protos[0], 0, 0, 0);
        tu_add_vertex(&s.protos[0], 1, 0, 0);
        tu_add_vertex(&s.protos[0], 0, 1, 0);
        tu_add_triangle(&s.protos[0], 0, 1, 2);
        identity(m);
        tu_add_instance(&s, 0, m);
        tu_add_instance(&s, 0, m);
        tu_add_instance(&s, 0, m);
        if (cases[c].entry == 0) m[5] = m[10] = 0.0f;
        if (cases[c].entry >= 0) m[cases[c].entry] = cases[c].value;
        tu_add_instance(&s, cases[c].proto, m);
        tu_instanced_source(&s, &src);
        EXPECT(brt_world_build(&src, &w, &err) == BRT_EARG && w == NULL &&
                   strstr(err.message, "instance 3") && strstr(err.message, cases[c].words),
               "case %zu: '%s'", c, err.message);
        tu_instanced_free(&s);
    }
}

/* The instanced hit file: header, 20-byte records, read back; the short
** writer refuses an instanced hit; a bad header or size is refused. */
static void test_hit_files(void)
{
    brt_hit hits[3], *back = NULL;
    const char *path = tu_scratch("inst.hits");
    unsigned char *bytes;
    size_t size = 0, count = 0;
    int instanced = -1;
    brt_error err;
    static const unsigned char header[16] = {0xE5, 0xA5, 0xB1, 0x7F, 'I', 'N', 'S', 'T', 1, 0, 0, 0, 20, 0, 0, 0};
    brt_hit_clear(&hits[0]);
    hits[1].t = 2.5f; hits[1].prim = 7; hits[1].u = 0.25f; hits[1].v = 0.5f; hits[1].inst = 3;
    hits[2] = hits[1];
    hits[2].inst = BRT_NO_INST;
    EXPECT(brt_hits_write(path, hits, 3, &err) == BRT_EARG && strstr(err.message, "hit 1"),
           "short form took an instanced hit: '%s'", err.message);
    CHECK(brt_hits_write_instanced(path, hits, 3, &err) == BRT_OK, "%s", err.message);
    bytes = tu_slurp(path, &size);
    EXPECT(bytes && size == 16 + 3 * 20 && memcmp(bytes, header, 16) == 0 &&
               bytes[16 + 20 + 16] == 3 && bytes[16 + 2 * 20 + 16] == 0xFF,
           "instanced file bytes");
    CHECK(brt_hits_read(path, &back, &count, &instanced, &err) == BRT_OK, "%s", err.message);
    EXPECT(count == 3 && instanced == 1 && memcmp(back, hits, sizeof hits) == 0, "read back differs");
    free(back);
    if (bytes && size > 20) {
        EXPECT(tu_spill(path, bytes, size - 1), "cannot write");
        EXPECT(brt_hits_read(path, &back, &count, NULL, &err) == BRT_EPARSE, "truncated record read");
        bytes[8] = 2;   /* version 2 */
        EXPECT(tu_spill(path, bytes, size), "cannot write");
        EXPECT(brt_hits_read(path, &back, &count, NULL, &err) == BRT_EPARSE &&
                   strstr(err.message, "header"), "version 2 read: '%s'", err.message);
    }
    free(bytes);
}

/* The margin (bvh.c, "Instances"): a rotated cube squashed to a
** thousandth in z (condition number about 1000).  The inverse stretches
** z by 1000 before it rotates, so rounding the object ray's origin, about
** ten thousand units out for an origin ten units away along z, moves the
** world ray sideways by 1000 u |o| -- far more than the box tests' own
** pads, so object-space hits lie outside the instance's world box and
** only the margin keeps them.  Rays come from ten units away, mostly
** along z, at points around the cube up to a third of its width off it. */
/* The scene and rays of the margin tests (above): n silhouette rays. */
static brt_ray *margin_case(tu_instanced *s, uint64_t *st, size_t n)
{
    const float ax[3] = {0.6f, 0.0f, 0.8f}, one[3] = {1, 1, 1}, at[3] = {0, 0, 0};
    float m[12], corner[3] = {0, 0, 0}, best = -INFINITY;
    brt_ray *rays = malloc(n * sizeof *rays);
    size_t i;
    int a, c;
    memset(s, 0, sizeof *s);
    adversarial_scene(s, st);   /* for its cube prototype (1) and world */
    s->instance_count = 0;
    rotation(m, ax, 0.4f, one, at);
    for (a = 0; a < 4; a++) m[8 + a] *= 2e-3f;   /* squash the rotated cube in z */
    tu_add_instance(s, 1, m);
    m[3] += 1000.0f;   /* a second one far off: a tree of instances, not one alone */
    tu_add_instance(s, 1, m);
    m[3] -= 1000.0f;
    for (c = 0; c < 8; c++) {   /* the corner farthest in +x: the silhouette */
        const float q[3] = {(float)(c & 1), (float)(c >> 1 & 1), (float)(c >> 2 & 1)};
        float p[3];
        for (a = 0; a < 3; a++) p[a] = m[4 * a] * q[0] + m[4 * a + 1] * q[1] + m[4 * a + 2] * q[2];
        if (p[0] > best) { best = p[0]; memcpy(corner, p, sizeof p); }
    }
    for (i = 0; rays && i < n; i++) {
        brt_ray *r = &rays[i];
        float d[3], target[3];
        tu_random_unit(st, d);
        d[0] *= 0.1f;
        d[1] *= 0.1f;
        d[2] = d[2] < 0 ? -1.0f : 1.0f;   /* mostly along z */
        target[0] = corner[0] + tu_rnd(st, -5e-4f, 2e-3f);
        target[1] = corner[1] + tu_rnd(st, -1e-3f, 1e-3f);
        target[2] = corner[2];
        for (a = 0; a < 3; a++) {
            r->org[a] = target[a] + 40.0f * d[a];
            r->dir[a] = target[a] - r->org[a];
        }
        r->tnear = 0.0f;
        r->tfar = INFINITY;
    }
    return rays;
}

static void test_margin_keeps_far_rays(void)
{
    enum { N = 20000 };
    tu_instanced s;
    brt_scene_source src;
    brt_world *w = NULL;
    brt_error err;
    uint64_t st = test_seed() + 2804;
    brt_ray *rays = margin_case(&s, &st, N);
    uint32_t i, hits = 0, bad = 0;
    CHECK(rays, "out of memory");
    tu_instanced_source(&s, &src);
    CHECK(brt_world_build(&src, &w, &err) == BRT_OK, "%s", err.message);
    for (i = 0; i < N; i++) {
        brt_hit want, got;
        brt_hit_clear(&want);
        brt_hit_clear(&got);
        tu_instanced_brute(&s, &rays[i], &want);
        brt_world_intersect(w, &rays[i], &got, NULL);
        hits += want.inst == 0;
        if (!same_hit(&want, &got) && bad++ < 3)
            test_fail_at(__FILE__, __LINE__, "ray %u: world t=%a inst %u, brute force t=%a inst %u",
                         (unsigned)i, got.t, (unsigned)got.inst, want.t, (unsigned)want.inst);
    }
    EXPECT(hits > 1000, "only %u rays hit the cube", (unsigned)hits);
    brt_world_free(w);
    tu_instanced_free(&s);
    free(rays);
}

/* Builds s's scene file with so, traces rays through it with opt and
** expects brt_world's hits byte for byte; checks the partition when
** point_tris is given (0: not).  Returns the scene's batching points. */
static uint32_t expect_batched_equals_direct(const tu_instanced *s, const brt_scene_options *so,
                                             const brt_trace_options *opt, const brt_ray *rays,
                                             size_t n, const char *name, uint32_t point_tris)
{
    brt_scene_source src;
    brt_world *w = NULL;
    brt_scene *scene = NULL;
    brt_error err;
    brt_hit *want = malloc(n * sizeof *want), *got = malloc(n * sizeof *got);
    uint32_t points = 0;
    tu_instanced_source(s, &src);
    if (!want || !got || brt_world_build(&src, &w, &err) != BRT_OK ||
        brt_scene_build_source(&src, so, 1, tu_scratch(name), &err) != BRT_OK ||
        brt_scene_open(tu_scratch(name), &scene, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s: %s", name, want && got ? err.message : "out of memory");
    } else {
        points = brt_scene_point_count(scene);
        if (point_tris && brt_scene_check_partition(scene, point_tris, &err) != BRT_OK)
            test_fail_at(__FILE__, __LINE__, "%s: %s", name, err.message);
        brt_world_trace(w, rays, NULL, n, want, NULL, 1);
        if (brt_scene_trace(scene, opt, rays, n, got, NULL, &err) != BRT_OK)
            test_fail_at(__FILE__, __LINE__, "%s: %s", name, err.message);
        else if (memcmp(want, got, n * sizeof *got) != 0)
            test_fail_at(__FILE__, __LINE__, "%s: batched differs from direct", name);
    }
    brt_scene_close(scene);
    brt_world_free(w);
    free(want);
    free(got);
    return points;
}

/* The same rays batched, at a resolution whose dilation is below their
** margin: the walk's boxes must grow by the margin, and the proxy must
** admit such rays untested (proxy_admits); the paper's scheduler asks
** the proxy at every visit. */
static void test_batched_margin(void)
{
    enum { N = 20000 };
    tu_instanced s;
    brt_scene_options so;
    brt_trace_options opt;
    uint64_t st = test_seed() + 2804;
    brt_ray *rays = margin_case(&s, &st, N);
    CHECK(rays, "out of memory");
    memset(&so, 0, sizeof so);
    so.point_tris = 1000;
    so.point_instanced = 12;   /* one instance per point: its box is the cube's */
    so.proxy_res = 512;
    memset(&opt, 0, sizeof opt);
    opt.paper_scheduler = 1;
    expect_batched_equals_direct(&s, &so, &opt, rays, N, "margin.brs", 0);
    tu_instanced_free(&s);
    free(rays);
}

/* brt_instance_ray rounds each component once: against long double, the
** error is at most half an ulp (u |exact|) plus what the double
** arithmetic adds, for origins near instances translated by 1e6. */
static void test_object_ray_rounded_once(void)
{
    uint64_t st = test_seed() + 2805;
    int i, bad = 0;
    for (i = 0; i < 20000; i++) {
        brt_instance in;
        brt_instance_frame f;
        brt_ray r, o;
        float d[3];
        int a, j;
        const float ax[3] = {0.0f, 0.6f, 0.8f}, sc[3] = {tu_rnd(&st, 0.5f, 2), 1, tu_rnd(&st, 0.5f, 2)};
        const float at[3] = {1e6f, -1e6f, tu_rnd(&st, -1e6f, 1e6f)};
        in.prototype = 0;
        rotation(in.xform, ax, tu_rnd(&st, 0, 6.28f), sc, at);
        if (brt_instance_frame_init(&in, 0, &f, NULL) != BRT_OK) continue;
        tu_random_unit(&st, d);
        for (a = 0; a < 3; a++) {
            r.org[a] = at[a] + tu_rnd(&st, -3, 3);
            r.dir[a] = d[a];
        }
        r.tnear = 0;
        r.tfar = INFINITY;
        brt_instance_ray(&f, &r, &o);
        for (a = 0; a < 3; a++) {
            long double exact = 0, mag = 0;
            for (j = 0; j < 3; j++) {
                const long double term = (long double)f.inverse[3 * a + j] *
                                         ((long double)r.org[j] - (long double)f.translation[j]);
                exact += term;
                mag += term < 0 ? -term : term;
            }
            if (fabsl((long double)o.org[a] - exact) > 0x1p-24L * fabsl(exact) + 0x1p-50L * mag &&
                bad++ < 3)
                test_fail_at(__FILE__, __LINE__, "ray %d axis %d: object origin %a not the exact %La rounded once",
                             i, a, o.org[a], exact);
        }
    }
}

/* ===================================================================== */
/* Batched mode (issue 28, part 2)                                       */
/* ===================================================================== */

/* Builds and opens the scene file of an instanced scene. */
static brt_scene *build_instanced(const tu_instanced *s, uint32_t point_tris, const char *name)
{
    brt_scene_source src;
    brt_scene_options opt;
    brt_scene *scene = NULL;
    brt_error err;
    memset(&opt, 0, sizeof opt);
    opt.point_tris = point_tris;
    opt.proxy_res = 32;
    tu_instanced_source(s, &src);
    if (brt_scene_build_source(&src, &opt, 7, tu_scratch(name), &err) != BRT_OK ||
        brt_scene_open(tu_scratch(name), &scene, &err) != BRT_OK)
        test_fail_at(__FILE__, __LINE__, "%s: %s", name, err.message);
    return scene;
}

/* Rays for the batched tests: ray_at every instance and the world. */
static brt_ray *instanced_rays(const tu_instanced *s, uint64_t *st, size_t n)
{
    brt_ray *rays = malloc(n * sizeof *rays);
    const uint32_t targets = s->instance_count + (s->world.tcount > 0);
    size_t i;
    for (i = 0; rays && i < n; i++) ray_at(s, (uint32_t)(i % targets), st, &rays[i]);
    return rays;
}

/* Batched == direct byte for byte over batch sizes, memory limits,
** proxies on and off, both schedulers and 1, 2 and 7 threads; the
** partition checker passes and culls happen (the proxies are asked). */
static void test_batched_equals_direct(void)
{
    enum { N = 4000 };
    static const uint32_t sizes[] = {40, 400, 100000};
    tu_instanced s;
    brt_scene_source src;
    brt_world *w = NULL;
    brt_error err;
    uint64_t st = test_seed() + 2810, culled = 0;
    brt_ray *rays;
    brt_hit *want = malloc(N * sizeof *want), *got = malloc(N * sizeof *got);
    size_t z;
    adversarial_scene(&s, &st);
    rays = instanced_rays(&s, &st, N);
    CHECK(rays && want && got, "out of memory");
    tu_instanced_source(&s, &src);
    CHECK(brt_world_build(&src, &w, &err) == BRT_OK, "%s", err.message);
    brt_world_trace(w, rays, NULL, N, want, NULL, 1);
    for (z = 0; z < sizeof sizes / sizeof sizes[0]; z++) {
        brt_scene *scene = build_instanced(&s, sizes[z], "inst.brs");
        int variant;
        if (!scene) break;
        EXPECT(brt_scene_check_partition(scene, sizes[z], &err) == BRT_OK, "batch %u: %s",
               (unsigned)sizes[z], err.message);
        for (variant = 0; variant < 12; variant++) {
            brt_trace_options opt;
            brt_stats stats;
            static const unsigned threads[3] = {1, 2, 7};
            memset(&opt, 0, sizeof opt);
            opt.memory_limit = variant % 3 == 0 ? 0 : variant % 3 == 1 ? 16384 : 200000;
            opt.no_proxy = variant % 4 == 3;
            opt.paper_scheduler = variant % 2;
            opt.threads = threads[variant % 3 == 0 ? (unsigned)variant / 3 % 3 : (unsigned)variant % 3];
            opt.rays_in_flight = 256;
            if (brt_scene_trace(scene, &opt, rays, N, got, &stats, &err) != BRT_OK) {
                test_fail_at(__FILE__, __LINE__, "batch %u variant %d: %s", (unsigned)sizes[z], variant,
                             err.message);
                break;
            }
            culled += stats.proxy_culled;
            if (memcmp(want, got, N * sizeof *got) != 0) {
                size_t i;
                for (i = 0; i < N && !memcmp(&want[i], &got[i], sizeof *got); i++) {}
                test_fail_at(__FILE__, __LINE__, "batch %u variant %d ray %zu: batched t=%a inst %u "
                             "prim %u, direct t=%a inst %u prim %u", (unsigned)sizes[z], variant, i,
                             got[i].t, (unsigned)got[i].inst, (unsigned)got[i].prim, want[i].t,
                             (unsigned)want[i].inst, (unsigned)want[i].prim);
                break;
            }
        }
        brt_scene_close(scene);
    }
    EXPECT(culled > 1000, "only %llu proxy culls: the proxies were hardly asked",
           (unsigned long long)culled);
    brt_world_free(w);
    tu_instanced_free(&s);
    free(rays); free(want); free(got);
}

/* A prototype's blob is read once however many points use it (no
** limit), prototype_loads counts it, and a point of instances holds at
** most point_tris triangles of distinct prototypes, unless it uses one. */
static void test_prototypes_loaded_once(void)
{
    enum { N = 3000 };
    tu_instanced s;
    brt_scene *scene;
    brt_trace_options opt;
    brt_stats stats;
    brt_error err;
    uint64_t st = test_seed() + 2811;
    brt_ray *rays;
    brt_hit *hits = malloc(N * sizeof *hits);
    adversarial_scene(&s, &st);
    rays = instanced_rays(&s, &st, N);
    scene = build_instanced(&s, 40, "once.brs");
    CHECK(scene && rays && hits, "set-up");
    EXPECT(brt_scene_point_count(scene) > 8, "only %u batching points", brt_scene_point_count(scene));
    memset(&opt, 0, sizeof opt);
    CHECK(brt_scene_trace(scene, &opt, rays, N, hits, &stats, &err) == BRT_OK, "%s", err.message);
    EXPECT(stats.prototype_loads == 3, "%llu prototype loads for 3 prototypes and no limit",
           (unsigned long long)stats.prototype_loads);
    opt.memory_limit = 8192;
    CHECK(brt_scene_trace(scene, &opt, rays, N, hits, &stats, &err) == BRT_OK, "%s", err.message);
    EXPECT(stats.prototype_loads > 3, "a tight limit reloads prototypes: %llu loads",
           (unsigned long long)stats.prototype_loads);
    brt_scene_close(scene);
    tu_instanced_free(&s);
    free(rays);
    free(hits);
}

/* The exact test of the proxies: with --exact-proxy every point's culls
** are exact, and a voxel proxy culls no ray the exact test keeps (it
** errs only towards "may hit"), counted over a scene whose points are
** instances only, so that every cull is an instance point's. */
static void test_proxy_culls_are_exact(void)
{
    enum { N = 4000 };
    tu_instanced s;
    brt_scene *scene;
    brt_trace_options opt;
    brt_stats voxel, exact;
    brt_error err;
    uint64_t st = test_seed() + 2812;
    brt_ray *rays;
    brt_hit *a = malloc(N * sizeof *a), *b = malloc(N * sizeof *b);
    adversarial_scene(&s, &st);
    tu_scene_free(&s.world);        /* instances only */
    rays = instanced_rays(&s, &st, N);
    scene = build_instanced(&s, 40, "exact.brs");
    CHECK(scene && rays && a && b, "set-up");
    memset(&opt, 0, sizeof opt);
    opt.paper_scheduler = 1;        /* every visit consults the proxy */
    CHECK(brt_scene_trace(scene, &opt, rays, N, a, &voxel, &err) == BRT_OK, "%s", err.message);
    opt.exact_proxies = 1;
    CHECK(brt_scene_trace(scene, &opt, rays, N, b, &exact, &err) == BRT_OK, "%s", err.message);
    EXPECT(memcmp(a, b, N * sizeof *a) == 0, "exact and voxel proxies give different hits");
    EXPECT(voxel.proxy_culled > 0 && voxel.proxy_culled <= exact.proxy_culled &&
               exact.proxy_tests >= exact.proxy_culled,
           "voxel proxies culled %llu of %llu, exact %llu of %llu",
           (unsigned long long)voxel.proxy_culled, (unsigned long long)voxel.proxy_tests,
           (unsigned long long)exact.proxy_culled, (unsigned long long)exact.proxy_tests);
    brt_scene_close(scene);
    tu_instanced_free(&s);
    free(rays); free(a); free(b);
}

/* ===================================================================== */
/* From outside: build/trace on a pbrt file with instances               */
/* ===================================================================== */

/* A pbrt-v4 file in the style of the paper's scenes: a ground of world
** triangles, a tree-like object of separate small triangles, instanced
** under translations, rotations and scales (and one mirror). */
static int write_pbrt_scene(void)
{
    static const char text[] =
        "# a small instanced scene; Scale -1 1 1: pbrt's image is then --camera's (rays.h)\n"
        "Scale -1 1 1 LookAt 0 5 -20  0 0 0  0 1 0\n"
        "Camera \"perspective\" \"float fov\" 45\n"
        "WorldBegin\n"
        "LightSource \"distant\" \"point3 from\" [0 10 0]\n"
        "Shape \"sphere\" \"float radius\" 2\n"
        "Shape \"trianglemesh\" \"point3 P\" [-10 0 -10 10 0 -10 10 0 10 -10 0 10]\n"
        "  \"integer indices\" [0 1 2 0 2 3]\n"
        "ObjectBegin \"plant\"\n"
        "  Shape \"trianglemesh\" \"point3 P\" [0 0 0 0.2 1 0 -0.2 1 0]\n"
        "  Translate 0 1 0\n"
        "  Shape \"trianglemesh\" \"point3 P\" [0 0 0 0.5 0.3 0.1 0.1 0.5 -0.3 0 0 0 -0.4 0.4 0.2 0.1 0.6 0.3]\n"
        "    \"integer indices\" [0 1 2 3 4 5]\n"
        "ObjectEnd\n"
        "AttributeBegin Translate -3 0 2 ObjectInstance \"plant\" AttributeEnd\n"
        "AttributeBegin Translate 1 0 -1 Rotate 40 0 1 0 Scale 2 2 2 ObjectInstance \"plant\" AttributeEnd\n"
        "AttributeBegin Translate 4 0 3 Rotate 90 1 0 0 ObjectInstance \"plant\" AttributeEnd\n"
        "AttributeBegin Translate 0 0 5 Scale -1 1 1 ObjectInstance \"plant\" AttributeEnd\n"
        "AttributeBegin Translate 0 0 5 Scale 1 1.5 1 ObjectInstance \"plant\" AttributeEnd\n";
    return tu_spill(tu_scratch("plants.pbrt"), text, sizeof text - 1);
}

/* Rays from above and from the side, across the plants. */
static int write_pbrt_rays(size_t n)
{
    brt_ray *rays = malloc(n * sizeof *rays);
    uint64_t st = test_seed() + 2820;
    size_t i;
    int ok;
    for (i = 0; rays && i < n; i++) {
        brt_ray *r = &rays[i];
        const float x = tu_rnd(&st, -6, 6), z = tu_rnd(&st, -4, 8), y = tu_rnd(&st, 0.1f, 3);
        if (i % 2) {
            r->org[0] = x; r->org[1] = 8; r->org[2] = z;
            r->dir[0] = tu_rnd(&st, -0.1f, 0.1f); r->dir[1] = -1; r->dir[2] = tu_rnd(&st, -0.1f, 0.1f);
        } else {
            r->org[0] = -12; r->org[1] = y; r->org[2] = z;
            r->dir[0] = 1; r->dir[1] = tu_rnd(&st, -0.05f, 0.05f); r->dir[2] = tu_rnd(&st, -0.2f, 0.2f);
        }
        r->tnear = 0;
        r->tfar = INFINITY;
    }
    ok = rays && brt_rays_write(tu_scratch("plants.rays"), rays, n, NULL) == BRT_OK;
    free(rays);
    return ok;
}

/* trace --direct and --batched (tiny points, a tight memory limit, 1 and
** 2 threads) write the same instanced hit file, and it names instances. */
static void test_trace_pbrt_instances(void)
{
    enum { N = 5000 };
    brt_hit *hits = NULL;
    size_t count = 0, i, on_instances = 0, inst_seen[5] = {0, 0, 0, 0, 0};
    int instanced = 0;
    unsigned char *a, *b;
    size_t na = 0, nb = 0;
    brt_error err;
    CHECK(write_pbrt_scene() && write_pbrt_rays(N), "cannot write the files");
    CHECK(tu_run("trace @/plants.pbrt @/plants.rays @/d.hits --direct --stats @/d.json") == 0,
          "direct: %s", tu_last_stderr());
    {   /* what the file had that batchrt skips, in the statistics too */
        char *json = (char *)tu_slurp(tu_scratch("d.json"), NULL);
        EXPECT(json && strstr(json, "\"skipped\": \"skipped: 1 LightSource, 1 Shape \\\"sphere\\\"\"") &&
                   tu_json_number(json, "rays") == N,
               "statistics: %s", json ? json : "(none)");
        free(json);
    }
    CHECK(tu_run("trace @/plants.pbrt @/plants.rays @/b.hits --batched --point-tris 3 --proxy-res 16 "
                 "--memory 8K --threads 2 --scene @/plants.brs") == 0, "batched: %s", tu_last_stderr());
    a = tu_slurp(tu_scratch("d.hits"), &na);
    b = tu_slurp(tu_scratch("b.hits"), &nb);
    EXPECT(a && b && na == nb && na == 16 + 20 * (size_t)N && memcmp(a, b, na) == 0,
           "direct and batched hit files differ (%zu and %zu bytes)", na, nb);
    free(a);
    free(b);
    CHECK(brt_hits_read(tu_scratch("d.hits"), &hits, &count, &instanced, &err) == BRT_OK, "%s",
          err.message);
    for (i = 0; i < count; i++)
        if (hits[i].inst != BRT_NO_INST) {
            on_instances++;
            if (hits[i].inst < 5) inst_seen[hits[i].inst]++;
        }
    EXPECT(instanced && count == N && on_instances > N / 100 && inst_seen[0] && inst_seen[1] &&
               inst_seen[2] && inst_seen[3] + inst_seen[4],
           "instanced %d, %zu of %zu hits on instances (%zu %zu %zu %zu %zu)", instanced,
           on_instances, count, inst_seen[0], inst_seen[1], inst_seen[2], inst_seen[3],
           inst_seen[4]);
    free(hits);
}

/* ===================================================================== */
/* Forged instanced scene files: every validator, each by its message    */
/* ===================================================================== */

static uint64_t le64(const unsigned char *p) { return brt_get_le64(p); }

/* Repairs every checksum of a version-4 file after a forgery: each point's
** and prototype's blob, the four sections, the header (inner first). */
static void repair_v4(unsigned char *f, size_t size)
{
    const uint64_t table = le64(f + 56), protos = le64(f + 128);
    const uint32_t points = brt_get_le32(f + 32), nproto = brt_get_le32(f + 44);
    uint32_t i;
    int sec;
    for (i = 0; i < points; i++) {
        unsigned char *e = f + table + 104 * (size_t)i;
        if (le64(e + 24) + le64(e + 32) <= size) brt_put_le64(e + 40, brt_checksum64(f + le64(e + 24), le64(e + 32)));
    }
    for (i = 0; i < nproto; i++) {
        unsigned char *e = f + protos + 56 * (size_t)i;
        if (le64(e) + le64(e + 8) <= size) brt_put_le64(e + 16, brt_checksum64(f + le64(e), le64(e + 8)));
    }
    for (sec = 0; sec < 4; sec++) {
        unsigned char *at = f + (sec < 3 ? 56 + 24 * sec : 128);
        if (le64(at) + le64(at + 8) <= size) brt_put_le64(at + 16, brt_checksum64(f + le64(at), le64(at + 8)));
    }
    brt_put_le64(f + 248, brt_checksum64(f, 248));
}

/* The first point of instances: its entry and its table. */
static unsigned char *instance_entry(unsigned char *f)
{
    uint32_t i, points = brt_get_le32(f + 32);
    for (i = 0; i < points; i++) {
        unsigned char *e = f + le64(f + 56) + 104 * (size_t)i;
        if (brt_get_le32(e + 80) > 1) return e;
    }
    return NULL;
}

typedef void (*forgery)(unsigned char *f, unsigned char *entry, unsigned char *table);

static void forge_magic(unsigned char *f, unsigned char *e, unsigned char *t) { (void)f; (void)e; t[3] ^= 1; }
static void forge_count(unsigned char *f, unsigned char *e, unsigned char *t) { (void)f; (void)e; brt_put_le32(t + 8, brt_get_le32(t + 8) + 1); }
/* The last listed prototype: one past the scene's (still ascending). */
static void forge_uses(unsigned char *f, unsigned char *e, unsigned char *t)
{
    (void)e;
    brt_put_le32(t + 32 + 4 * (size_t)(brt_get_le32(t + 16) - 1), brt_get_le32(f + 44));
}
/* The entry's count of instances one short of its table's. */
static void forge_entry_count(unsigned char *f, unsigned char *e, unsigned char *t)
{
    (void)f; (void)t;
    brt_put_le32(e + 80, brt_get_le32(e + 80) - 1);
}
/* The first record: its instance number beyond the scene's. */
static unsigned char *first_record(unsigned char *t)
{
    return t + 32 + ((size_t)brt_get_le32(t + 16) * 4 + 7) / 8 * 8;
}
static void forge_number(unsigned char *f, unsigned char *e, unsigned char *t) { (void)e; brt_put_le32(first_record(t), brt_get_le32(f + 152)); }
static void forge_singular(unsigned char *f, unsigned char *e, unsigned char *t)
{
    unsigned char *r = first_record(t) + 8;
    int k;
    (void)f; (void)e;
    for (k = 0; k < 4; k++) brt_put_le32(r + 16 + 4 * k, 0);   /* the second row: zero */
}
static unsigned char *first_node(unsigned char *t)
{
    return first_record(t) + 56 * (size_t)brt_get_le32(t + 8);
}
static void forge_leaf(unsigned char *f, unsigned char *e, unsigned char *t)
{
    unsigned char *n = first_node(t);
    uint32_t nodes = brt_get_le32(t + 12), k;
    (void)f; (void)e;
    for (k = 0; k < 4 * nodes; k++)   /* the first leaf names a record past the last */
        if (brt_get_le32(n + 4 * (size_t)k) & 0x80000000u) {
            brt_put_le32(n + 4 * (size_t)k, 0x80000000u | brt_get_le32(t + 8));
            return;
        }
}
static void forge_child(unsigned char *f, unsigned char *e, unsigned char *t)
{
    (void)f; (void)e;
    brt_put_le32(first_node(t), 0);   /* the root names itself */
}
static void forge_margin(unsigned char *f, unsigned char *e, unsigned char *t)
{
    (void)f; (void)t;
    brt_put_le32(e + 96, 0);   /* reach 0: smaller than the instances' */
}

/* Each forgery of an instance table is refused at its load with a message
** naming the point and the part; the file is otherwise intact (checksums
** repaired), and a fresh copy traces without error. */
static void test_forged_instance_tables(void)
{
    static const struct { forgery forge; const char *words; } cases[] = {
        {forge_magic, "bad magic"},
        {forge_count, "counts disagree"},
        {forge_entry_count, "counts disagree"},
        {forge_uses, "prototype list"},
        {forge_number, "instance number or prototype out of range"},
        {forge_singular, "singular"},
        {forge_leaf, "tree leaf"},
        {forge_child, "tree child"},
        {forge_margin, "margin smaller"},
    };
    enum { N = 2000 };
    tu_instanced s;
    uint64_t st = test_seed() + 2830;
    brt_scene *scene;
    brt_ray *rays;
    brt_hit *hits = malloc(N * sizeof *hits);
    unsigned char *good;
    size_t size = 0, c;
    adversarial_scene(&s, &st);
    rays = instanced_rays(&s, &st, N);
    scene = build_instanced(&s, 100000, "forged.brs");
    CHECK(scene && rays && hits, "set-up");
    brt_scene_close(scene);
    good = tu_slurp(tu_scratch("forged.brs"), &size);
    CHECK(good && instance_entry(good), "no point of instances in the file");
    for (c = 0; c < sizeof cases / sizeof cases[0]; c++) {
        unsigned char *f = malloc(size), *e;
        brt_trace_options opt;
        brt_error err;
        brt_result r;
        memcpy(f, good, size);
        err.message[0] = 0;
        e = instance_entry(f);
        cases[c].forge(f, e, f + le64(e + 24));
        repair_v4(f, size);
        CHECK(tu_spill(tu_scratch("forged2.brs"), f, size), "cannot write");
        free(f);
        r = brt_scene_open(tu_scratch("forged2.brs"), &scene, &err);
        if (r == BRT_OK) {
            memset(&opt, 0, sizeof opt);
            opt.no_proxy = 1;   /* every point is loaded */
            r = brt_scene_trace(scene, &opt, rays, N, hits, NULL, &err);
            brt_scene_close(scene);
        }
        EXPECT(r == BRT_EFORMAT && strstr(err.message, cases[c].words) &&
                   strstr(err.message, "forged2.brs"),
               "case %zu: result %d, '%s' (expected '%s')", c, (int)r, err.message, cases[c].words);
    }
    free(good);
    tu_instanced_free(&s);
    free(rays);
    free(hits);
}

/* The referee's transform class (examples/lib/referee.h): a record within
** the rounding of the ray's transform is explained, a fabricated one is
** not.  One instance of a unit square, moved and rotated; a ray through
** its inside from fifty units away. */
static void test_referee_transform_class(void)
{
    tu_instanced s;
    brt_scene_source src;
    ex_instanced_mesh m;
    brt_error err;
    ex_verdict v;
    brt_hit right, shifted, far, miss, world;
    const float ax[3] = {0, 1, 0}, one[3] = {1, 1, 1}, at[3] = {100, 0, 0};
    float xf[12];
    brt_ray r = {{100.5f, 50, 0.5f}, {0, -1, 0}, 0, INFINITY};
    memset(&s, 0, sizeof s);
    s.proto_count = 1;
    tu_add_vertex(&s.protos[0], 0, 0, 0);
    tu_add_vertex(&s.protos[0], 1, 0, 0);
    tu_add_vertex(&s.protos[0], 1, 0, 1);
    tu_add_vertex(&s.protos[0], 0, 0, 1);
    tu_add_triangle(&s.protos[0], 0, 1, 2);
    tu_add_triangle(&s.protos[0], 0, 2, 3);
    tu_add_vertex(&s.world, 90, -5, -10);   /* a floor far below */
    tu_add_vertex(&s.world, 110, -5, -10);
    tu_add_vertex(&s.world, 100, -5, 10);
    tu_add_triangle(&s.world, 0, 1, 2);
    rotation(xf, ax, 0.3f, one, at);
    tu_add_instance(&s, 0, xf);
    tu_instanced_source(&s, &src);
    CHECK(ex_instanced_mesh_load(&src, &m, &err) == BRT_OK, "%s", err.message);
    r.org[0] = 100.0f + 0.25f * xf[0] + 0.6f * xf[2];   /* (0.25, 0.6): inside, off the diagonal */
    r.org[2] = 0.25f * xf[8] + 0.6f * xf[10];
    brt_hit_clear(&right);
    tu_instanced_brute(&s, &r, &right);
    CHECK(right.inst == 0, "the ray misses the instance");
    shifted = right;
    shifted.t = nextafterf(nextafterf(right.t, INFINITY), INFINITY);
    far = right;
    far.t = right.t + 1.0f;
    brt_hit_clear(&miss);
    brt_hit_clear(&world);
    tu_brute_force(&s.world, NULL, &r, &world);
    EXPECT(ex_referee_instanced(&m, &r, &right, &shifted, &v) != EX_UNEXPLAINED,
           "two ulps of t: %s", v.text);
    EXPECT(ex_referee_instanced(&m, &r, &right, &far, &v) == EX_UNEXPLAINED, "t one unit off: %s",
           v.text);
    EXPECT(ex_referee_instanced(&m, &r, &right, &miss, &v) == EX_UNEXPLAINED,
           "a miss through the square's middle: %s", v.text);
    EXPECT(world.prim == 0 && ex_referee_instanced(&m, &r, &right, &world, &v) == EX_UNEXPLAINED,
           "the floor instead of the nearer square: %s", v.text);
    {   /* a ray three units beside the square, and a record claiming it */
        brt_ray beside = r;
        brt_hit none;
        beside.org[0] += 3.0f;
        brt_hit_clear(&none);
        EXPECT(ex_referee_instanced(&m, &beside, &right, &none, &v) == EX_UNEXPLAINED,
               "a hit on a square the ray passes three units from: %s", v.text);
    }
    ex_instanced_mesh_free(&m);
    tu_instanced_free(&s);
}

/* One instance under the identity is the mesh itself: the object ray is
** the world ray, float for float (o - 0 and the identity, in double, round
** back to the same floats), so every hit is the mesh's but for inst. */
static void test_identity_instance_is_the_mesh(void)
{
    enum { N = 20000 };
    tu_instanced mesh_scene, inst_scene;
    brt_scene_source a, b;
    brt_world *wa = NULL, *wb = NULL;
    brt_error err;
    uint64_t st = test_seed() + 2840;
    float m[12], lo[3], hi[3];
    size_t i, bad = 0, hits = 0;
    memset(&mesh_scene, 0, sizeof mesh_scene);
    memset(&inst_scene, 0, sizeof inst_scene);
    tu_random_soup(&mesh_scene.world, &st, 2000, 0.05f);
    inst_scene.proto_count = 1;
    st = test_seed() + 2840;   /* the same soup again */
    tu_random_soup(&inst_scene.protos[0], &st, 2000, 0.05f);
    identity(m);
    tu_add_instance(&inst_scene, 0, m);
    tu_instanced_source(&mesh_scene, &a);
    tu_instanced_source(&inst_scene, &b);
    CHECK(brt_world_build(&a, &wa, &err) == BRT_OK && brt_world_build(&b, &wb, &err) == BRT_OK,
          "%s", err.message);
    tu_scene_bounds(&mesh_scene.world, lo, hi);
    for (i = 0; i < N; i++) {
        brt_ray r;
        brt_hit x, y;
        tu_make_ray(&mesh_scene.world, lo, hi, (int)(i % TU_RAY_KINDS), &st, &r);
        brt_hit_clear(&x);
        brt_hit_clear(&y);
        brt_world_intersect(wa, &r, &x, NULL);
        brt_world_intersect(wb, &r, &y, NULL);
        hits += x.prim != BRT_NO_PRIM;
        if (x.prim != BRT_NO_PRIM) y.inst = y.inst == 0 ? BRT_NO_INST : 7;
        bad += memcmp(&x, &y, sizeof x) != 0;
    }
    EXPECT(bad == 0 && hits > N / 4, "%zu of %zu rays differ (%zu hits)", bad, (size_t)N, hits);
    brt_world_free(wa);
    brt_world_free(wb);
    tu_instanced_free(&mesh_scene);
    tu_instanced_free(&inst_scene);
}

/* The instance pass out of core (scene.c, "instance points"): with
** buckets of a few instances (brt_test_build_sizes), 3000 instances of three
** prototypes scattered over a plane go through the spill file's Morton
** buckets; every instance lands in exactly one batching point (the
** partition checker), no point spans two buckets' worth, and batched ==
** direct, byte for byte. */
static void test_instance_buckets(void)
{
    enum { N = 4000, INSTANCES = 3000 };
    tu_instanced s;
    brt_scene_options so;
    brt_trace_options opt;
    uint64_t st = test_seed() + 2850;
    brt_ray *rays;
    uint32_t i, points;
    adversarial_scene(&s, &st);
    s.instance_count = 0;
    for (i = 0; i < INSTANCES; i++) {
        const float ax[3] = {0, 1, 0}, sc[3] = {0.5f, 0.5f, 0.5f};
        const float at[3] = {tu_rnd(&st, -50, 50), tu_rnd(&st, -1, 1), tu_rnd(&st, -50, 50)};
        float m[12];
        rotation(m, ax, tu_rnd(&st, 0, 6.28f), sc, at);
        tu_add_instance(&s, i % 3, m);
    }
    rays = instanced_rays(&s, &st, N);
    CHECK(rays, "out of memory");
    memset(&so, 0, sizeof so);
    so.point_tris = 100000;          /* points cut by the buckets alone */
    so.proxy_res = 16;
    brt_test_build_sizes(7, 64);     /* chunks of 7, instance buckets of 16 */
    memset(&opt, 0, sizeof opt);
    opt.memory_limit = 50000;
    points = expect_batched_equals_direct(&s, &so, &opt, rays, N, "buckets.brs", 100000);
    EXPECT(points >= INSTANCES / 16, "%u batching points for %u instances in buckets of 16", points,
           INSTANCES);
    tu_instanced_free(&s);
    free(rays);
}

/* render's default view of a pbrt file is the file's camera: pbrt's fov
** spans the shorter side, render's the longer, so the file's fov 45 on a
** 64x32 image is --camera with 2 atan(2 tan 22.5 deg) = 79.28 degrees; the
** images agree but for the last bits of the camera's arithmetic. */
static void test_render_pbrt_camera(void)
{
    unsigned char *a, *b, *pa = NULL, *pb = NULL;
    size_t na = 0, nb = 0, i, close = 0;
    int wa = 0, ha = 0, wb = 0, hb = 0;
    CHECK(write_pbrt_scene(), "cannot write the scene");
    CHECK(tu_run("render @/plants.pbrt --width 64 --height 32 --spp 2 --direct --out @/cam_a.png") == 0,
          "render: %s", tu_last_stderr());
    CHECK(tu_run("render @/plants.pbrt --width 64 --height 32 --spp 2 --direct --out @/cam_b.png "
                 "--camera 0,5,-20:0,0,0:79.27854") == 0, "render --camera: %s", tu_last_stderr());
    a = tu_slurp(tu_scratch("cam_a.png"), &na);
    b = tu_slurp(tu_scratch("cam_b.png"), &nb);
    if (a) pa = tu_png_decode(a, na, &wa, &ha);
    if (b) pb = tu_png_decode(b, nb, &wb, &hb);
    CHECK(pa && pb && wa == 64 && ha == 32 && wb == 64 && hb == 32, "cannot decode the images");
    for (i = 0; i < 3 * 64 * 32; i++) close += abs((int)pa[i] - (int)pb[i]) <= 2;
    EXPECT(close >= 3 * 64 * 32 * 98 / 100, "only %zu of %d channels agree", close, 3 * 64 * 32);
    free(a); free(b); free(pa); free(pb);
}

/* The analysis programs read a pbrt file flattened: the plants scene's 2
** world triangles and 5 instances of a 3-triangle object are 17. */
static void test_flattened_pbrt(void)
{
    char *out;
    CHECK(write_pbrt_scene(), "cannot write the scene");
    CHECK(tu_run("closed @/plants.pbrt") == 0, "closed: %s", tu_last_stderr());
    out = tu_last_stdout();
    EXPECT(out && strstr(out, ": 17 triangles"), "closed says: %s", out ? out : "(nothing)");
    free(out);
    EXPECT(tu_run("voxelize @/plants.pbrt --proxy-res 16") == 0, "voxelize: %s", tu_last_stderr());
}

/* The virtual size of this process in pages (Linux's /proc/self/statm), or
** 0 where there is none. */
static unsigned long mapped_pages(void)
{
    unsigned long pages = 0;
    FILE *f = fopen("/proc/self/statm", "r");
    if (f && fscanf(f, "%lu", &pages) != 1) pages = 0;
    if (f) fclose(f);
    return pages;
}

/* In a child whose address space may not grow (RLIMIT_AS at its size,
** after a heap block freed for the small allocations), opening point id's
** table cannot map its arrays: out of memory, not a crash. */
static void table_open_unmappable(const brt_scene *scene, uint32_t id, const unsigned char *data, uint64_t size)
{
    int status = 0;
    pid_t child;
    fflush(NULL);
    child = fork();
    CHECK(child >= 0, "fork");
    if (child == 0) {
        struct rlimit limit;
        instance_set *set = NULL;
        brt_error err;
        brt_result r;
        free(malloc(64 << 10));
        getrlimit(RLIMIT_AS, &limit);
        limit.rlim_cur = (rlim_t)mapped_pages() * (rlim_t)sysconf(_SC_PAGESIZE);
        if (setrlimit(RLIMIT_AS, &limit) != 0) _exit(4);
        r = brt_instance_table_open(scene, id, data, size, &set, &err);
        _exit(r == BRT_ENOMEM ? 0 : r == BRT_OK ? 2 : 3);
    }
    CHECK(waitpid(child, &status, 0) == child, "waitpid");
    EXPECT(WIFEXITED(status) && WEXITSTATUS(status) == 0, "a table that cannot be mapped: %s %d (want exit 0: "
           "out of memory)", WIFEXITED(status) ? "exit" : "signal",
           WIFEXITED(status) ? WEXITSTATUS(status) : WTERMSIG(status));
}

/* A loaded instance table (brt_instance_table_open, what the cache opens
** at each load of a point of instances): its five arrays lie in its one
** mapping without overlap and fill it exactly, and freeing it gives the
** whole mapping back -- 300 loads and frees leave the process no larger;
** one that cannot be mapped is out of memory (Linux: /proc/self/statm;
** not under a sanitizer or valgrind, whose own mappings would grow). */
static void test_instance_table_mapping(void)
{
    const char *path = tu_scratch("tables.brs");
    brt_scene *scene = NULL;
    brt_error err;
    uint32_t id, tested = 0;
    const int rss = tu_rss_is_meaningful();   /* not under a sanitizer or valgrind */
    CHECK(tu_run("render landscape --scale 0.3 --spp 1 --width 4 --height 4 --point-tris 100000 "
                 "--point-instanced 400000 --scene @/tables.brs --out @/t.png") == 0, "render failed");
    CHECK(brt_scene_open(path, &scene, &err) == BRT_OK, "%s", err.message);
    for (id = 0; id < scene->header.point_count && tested < 3; id++) {
        const blob_place *b = &scene->blobs[id];
        unsigned char *data;
        instance_set *set = NULL;
        unsigned long before = 0;
        int i;
        if (!scene->points[id].instances) continue;
        data = malloc((size_t)b->size);
        CHECK(data && pread(scene->fd, data, (size_t)b->size, (off_t)b->offset) == (ssize_t)b->size, "read");
        for (i = 0; i < 300 && !test_failed(); i++) {
            CHECK(brt_instance_table_open(scene, id, data, b->size, &set, &err) == BRT_OK, "%s", err.message);
            if (i == 0) {
                const unsigned char *at = set->mapping, *end = at + set->mapping_bytes;
                const size_t n = set->count, m = set->node_count, k = set->use_count;
                EXPECT(set->mapping && (const unsigned char *)set->nodes == at &&
                       (const unsigned char *)(set->nodes + m) <= (const unsigned char *)set->frames &&
                       (const unsigned char *)(set->frames + n) <= (const unsigned char *)set->ids &&
                       set->ids + n <= set->prototypes && set->prototypes + n <= set->uses &&
                       (const unsigned char *)(set->uses + k) == end,
                       "point %u: the arrays of %lu instances, %lu nodes and %lu uses do not tile its %lu-byte "
                       "mapping", (unsigned)id, (unsigned long)n, (unsigned long)m, (unsigned long)k,
                       (unsigned long)set->mapping_bytes);
                before = rss ? mapped_pages() : 0;
            }
            brt_set_free(set);
            free(set);
        }
        if (before)
            EXPECT(mapped_pages() <= before + 16, "point %u: 300 loads grew the process by %lu pages", (unsigned)id,
                   mapped_pages() - before);
        if (before && tested == 0) table_open_unmappable(scene, id, data, b->size);
        free(data);
        tested++;
    }
    EXPECT(tested > 0, "no point of instances");
    brt_scene_close(scene);
}

void suite_instances(void)
{
    test_run("instances: direct equals brute force on adversarial transforms",
             test_direct_equals_brute_force);
    test_run("instances: a loaded instance table tiles one mapping, freed whole", test_instance_table_mapping);
    test_run("instances: brt_world_trace at 1 and 7 threads", test_trace_threads);
    test_run("instances: world normals", test_world_normals);
    test_run("instances: the margin keeps far rays' hits", test_margin_keeps_far_rays);
    test_run("instances: tie-break (t, inst, prim)", test_tie_break);
    test_run("instances: a tie won by the lower instance carries its normal", test_tie_carries_normal);
    test_run("instances: the object ray is rounded once", test_object_ray_rounded_once);
    test_run("instances: bad instances refused, naming the instance", test_bad_instances);
    test_run("instances: instanced hit files", test_hit_files);
    test_run("instances: batched equals direct over sizes, limits, proxies, threads",
             test_batched_equals_direct);
    test_run("instances: a prototype is read once", test_prototypes_loaded_once);
    test_run("instances: batched margin: far rays keep their hits", test_batched_margin);
    test_run("instances: proxy culls within the exact test's", test_proxy_culls_are_exact);
    test_run("instances: trace on a pbrt file, direct == batched", test_trace_pbrt_instances);
    test_run("instances: forged instance tables refused at load", test_forged_instance_tables);
    test_run("instances: the referee's transform class", test_referee_transform_class);
    test_run("instances: one identity instance is the mesh", test_identity_instance_is_the_mesh);
    test_run("instances: the instance pass in buckets (out of core)", test_instance_buckets);
    test_run("instances: render's view of a pbrt file is its camera", test_render_pbrt_camera);
    test_run("instances: voxelize and closed read a pbrt file flattened", test_flattened_pbrt);
}
