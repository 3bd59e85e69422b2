/*
** tests/test_cli.c -- the command-line contracts of README.md, checked from
** outside: the programs in $BRT_BUILD (default "build") run through
** system() on small meshes generated into the scratch directory, and their
** files are compared with independent oracles written here (a brute-force
** loop over brt_intersect_triangle for hits, geometry for rays, a
** self-written PNG decoder for the PNG writer of examples/lib/common.c).
**
** Out of core from end to end (README, same title): batched runs work from the
** scene file alone (the mesh file replaced by garbage, its stamp kept),
** every program's statistics carry peak_rss_bytes, SIGINT and SIGTERM
** leave no temporary file behind, and trace --batched equals --direct on
** every built-in scene through the streamed build.
*/
#include "test.h"
#include "batchrt.h"
#include "util.h"
#include "../examples/lib/common.h"

#include <dirent.h>
#include <math.h>
#include <stdarg.h>
#include <stdlib.h>
#include <string.h>
#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

/* ===================================================================== */
/* Test meshes and record codecs                                         */
/* ===================================================================== */

/* "%.9g" round-trips every float, so the loader sees exactly m's values. */
static int write_obj(const char *path, const tu_scene *m)
{
    FILE *f = fopen(path, "w");
    uint32_t i;
    if (!f) return 0;
    for (i = 0; i < m->vcount; i++)
        fprintf(f, "v %.9g %.9g %.9g\n", m->pos[3 * i], m->pos[3 * i + 1], m->pos[3 * i + 2]);
    for (i = 0; i < m->tcount; i++)
        fprintf(f, "f %u %u %u\n", (unsigned)m->idx[3 * i] + 1, (unsigned)m->idx[3 * i + 1] + 1,
                (unsigned)m->idx[3 * i + 2] + 1);
    return fclose(f) == 0;
}

/* A lumpy closed sphere (random radii per vertex) plus a random soup of
** triangles through it, an exact duplicate (equal t: the tie-break decides)
** and a degenerate triangle: every kind of ray finds something to hit. */
static void make_lumpy_mesh(tu_scene *m, uint64_t *rng)
{
    const int stacks = 12, slices = 24;
    const double pi = 3.14159265358979323846;
    uint32_t north, south;
    int i, j;
    north = tu_add_vertex(m, 0, 1, 0);
    for (i = 1; i < stacks; i++)
        for (j = 0; j < slices; j++) {
            double th = pi * i / stacks, ph = 2 * pi * j / slices;
            double r = 1.0 + 0.2 * brt_random_float(rng);
            tu_add_vertex(m, (float)(r * sin(th) * cos(ph)), (float)(r * cos(th)),
                          (float)(r * sin(th) * sin(ph)));
        }
    south = tu_add_vertex(m, 0, -1, 0);
    for (j = 0; j < slices; j++) {
        uint32_t j1 = (uint32_t)((j + 1) % slices);
        tu_add_triangle(m, north, 1 + j1, 1 + (uint32_t)j);
        tu_add_triangle(m, south, 1 + (uint32_t)((stacks - 2) * slices + j),
                        1 + (uint32_t)((stacks - 2) * slices) + j1);
        for (i = 0; i + 2 < stacks; i++) {
            uint32_t a = 1 + (uint32_t)(i * slices + j), b = 1 + (uint32_t)(i * slices) + j1;
            tu_add_triangle(m, a, b, b + (uint32_t)slices);
            tu_add_triangle(m, a, b + (uint32_t)slices, a + (uint32_t)slices);
        }
    }
    for (i = 0; i < 60; i++) {
        float x = tu_rnd(rng, -1.2f, 1.2f), y = tu_rnd(rng, -1.2f, 1.2f);
        float z = tu_rnd(rng, -1.2f, 1.2f);
        uint32_t a = tu_add_vertex(m, x, y, z);
        tu_add_vertex(m, x + tu_rnd(rng, 0, 0.5f), y + tu_rnd(rng, 0, 0.5f), z);
        tu_add_vertex(m, x, y + tu_rnd(rng, 0, 0.5f), z + tu_rnd(rng, 0, 0.5f));
        tu_add_triangle(m, a, a + 1, a + 2);
    }
    tu_add_triangle(m, m->idx[3 * 5], m->idx[3 * 5 + 1], m->idx[3 * 5 + 2]);
    tu_add_triangle(m, north, north, south);
}

/* The cube [-1,1]^3, 12 triangles, outward winding irrelevant. */
static void make_cube(tu_scene *m)
{
    static const int quads[6][4] = {{0, 1, 3, 2}, {4, 6, 7, 5}, {0, 4, 5, 1},
                                    {2, 3, 7, 6}, {0, 2, 6, 4}, {1, 5, 7, 3}};
    int i;
    for (i = 0; i < 8; i++)
        tu_add_vertex(m, i & 1 ? 1.0f : -1.0f, i & 2 ? 1.0f : -1.0f, i & 4 ? 1.0f : -1.0f);
    for (i = 0; i < 6; i++) {
        tu_add_triangle(m, (uint32_t)quads[i][0], (uint32_t)quads[i][1], (uint32_t)quads[i][2]);
        tu_add_triangle(m, (uint32_t)quads[i][0], (uint32_t)quads[i][2], (uint32_t)quads[i][3]);
    }
}

/* Writes the cube as an OBJ file NAME in the scratch directory. */
static int write_cube(const char *name)
{
    tu_scene cube = {0};
    int ok;
    make_cube(&cube);
    ok = write_obj(tu_scratch(name), &cube);
    tu_scene_free(&cube);
    return ok;
}

static uint32_t get_le32(const unsigned char *p)
{
    return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}

static void put_le32(unsigned char *p, uint32_t x)
{
    p[0] = (unsigned char)x; p[1] = (unsigned char)(x >> 8);
    p[2] = (unsigned char)(x >> 16); p[3] = (unsigned char)(x >> 24);
}

static float get_f32(const unsigned char *p)
{
    uint32_t bits = get_le32(p);
    float f;
    memcpy(&f, &bits, 4);
    return f;
}

static void put_f32(unsigned char *p, float f)
{
    uint32_t bits;
    memcpy(&bits, &f, 4);
    put_le32(p, bits);
}

/* Decodes a ray file by hand (32-byte little-endian records). */
static brt_ray *load_rays(const char *path, size_t *count)
{
    size_t size, i;
    int k;
    unsigned char *data = tu_slurp(path, &size);
    brt_ray *rays;
    if (!data || size % 32 != 0 || !(rays = malloc(size / 32 * sizeof *rays + 1))) {
        free(data);
        return NULL;
    }
    for (i = 0; i < size / 32; i++) {
        for (k = 0; k < 3; k++) {
            rays[i].org[k] = get_f32(data + 32 * i + 4 * k);
            rays[i].dir[k] = get_f32(data + 32 * i + 12 + 4 * k);
        }
        rays[i].tnear = get_f32(data + 32 * i + 24);
        rays[i].tfar = get_f32(data + 32 * i + 28);
    }
    free(data);
    *count = size / 32;
    return rays;
}

/* The oracle: every triangle in turn, closest hit, lowest prim on ties. */
static brt_hit brute_force_hit(const tu_scene *m, const brt_ray *ray)
{
    brt_hit hit;
    brt_hit_clear(&hit);
    tu_brute_force(m, NULL, ray, &hit);
    return hit;
}

static double length3f(const float v[3])
{
    return sqrt((double)v[0] * v[0] + (double)v[1] * v[1] + (double)v[2] * v[2]);
}

/* Common checks of every raygen kind: unit directions, tnear 0, tfar +inf.
** Records a failure for the first bad ray and returns 0 then. */
static int rays_are_unit_and_unbounded(const brt_ray *rays, size_t count)
{
    size_t i;
    for (i = 0; i < count; i++) {
        const brt_ray *r = &rays[i];
        if (fabs(length3f(r->dir) - 1.0) > 1e-6 || r->tnear != 0.0f || !(r->tfar == INFINITY)) {
            test_fail_at(__FILE__, __LINE__, "ray %lu: |dir| = %.9g, tnear %g, tfar %g",
                         (unsigned long)i, length3f(r->dir), r->tnear, r->tfar);
            return 0;
        }
    }
    return 1;
}

/* Writes the test meshes and returns nonzero on success. */
static int write_lumpy_mesh(tu_scene *m, const char *name)
{
    uint64_t rng = test_seed();
    make_lumpy_mesh(m, &rng);
    return write_obj(tu_scratch(name), m);
}

/* ===================================================================== */
/* Tests                                                                 */
/* ===================================================================== */

/* README, "Programs": an option renamed since is named by its new name in
** one line -- every program that took --res (embree_trace when built) --
** and an option no program ever had is still unknown. */
static void test_renamed_options(void)
{
    static const char *const programs[] = {"trace", "render", "voxelize", "bench_svdag", "bench_batched",
                                           "figures", "embree_trace"};
    static const char *const renamed[][2] = {
        {"--res", "--proxy-res"}, {"--batch-tris", "--point-tris"}, {"--batch-instanced", "--point-instanced"}};
    const char *build = getenv("BRT_BUILD") ? getenv("BRT_BUILD") : "build";
    char embree[600], *err;
    size_t i, k;
    snprintf(embree, sizeof embree, "%s/embree_trace", build);
    for (i = 0; i < sizeof programs / sizeof *programs; i++)
        for (k = 0; k < sizeof renamed / sizeof *renamed; k++) {
            char want[128];
            int status;
            if (strcmp(programs[i], "embree_trace") == 0 && !tu_file_exists(embree)) continue;
            status = tu_run("%s %s 8 x.obj x.rays x.hits", programs[i], renamed[k][0]);
            err = tu_last_stderr();
            snprintf(want, sizeof want, "%s: %s is now %s (see --help)\n", programs[i], renamed[k][0],
                     renamed[k][1]);
            EXPECT(status == 1 && err && strcmp(err, want) == 0, "%s %s: exit %d, said '%s', want '%s'",
                   programs[i], renamed[k][0], status, err ? err : "", want);
            free(err);
        }
    EXPECT(tu_run("trace x.obj x.rays x.hits --resolution 8") == 1, "trace --resolution accepted");
    err = tu_last_stderr();
    EXPECT(err && strcmp(err, "trace: unknown option '--resolution' (see --help)\n") == 0, "trace --resolution: %s",
           err ? err : "");
    free(err);
}

static void test_help(void)
{
    /* Every program make builds (the Makefile's PROGRAMS: examples/tutorials,
    ** tools and bench). */
    static const char *const programs[] = {"trace", "raygen", "hitdiff", "minimal", "minimal_batched",
                                           "closed", "render", "mkscene", "figures", "voxelize",
                                           "bench_bvh", "bench_svdag", "bench_batched", "bench_pbrt",
                                           "bench_order"};
    size_t i;
    char *list;
    /* ... every one: a file of examples/ with a main() is in the list
    ** (the optional Embree and MPI tracers aside), and none is in lib/. */
    CHECK(tu_shell("grep -l '^int main(' examples/*/*.c | sed 's|^examples/lib/|lib:|; s|.*/||; s|[.]c$||' | "
                   "grep -v '^embree_trace$' | grep -v '^mpi_trace$'", "", "") == 0, "cannot list examples/");
    list = tu_last_stdout();
    CHECK(list, "no list of programs");
    {
        char *name = strtok(list, "\n");
        for (; name; name = strtok(NULL, "\n")) {
            int known = 0;
            for (i = 0; i < sizeof programs / sizeof *programs; i++) known |= strcmp(programs[i], name) == 0;
            EXPECT(known, "program %s is not in the --help test's list", name);
        }
    }
    free(list);
    for (i = 0; i < sizeof programs / sizeof *programs; i++) {
        char *out;
        int status = tu_run("%s --help", programs[i]);
        out = tu_last_stdout();
        EXPECT(status == 0, "%s --help: exit status %d", programs[i], status);
        EXPECT(out && strstr(out, "usage:"), "%s --help: no usage on stdout", programs[i]);
        free(out);
    }
}

static void test_minimal(void)
{
    char *out;
    int status = tu_run("minimal");
    out = tu_last_stdout();
    /* Five rays down the quad's anti-diagonal all hit it. */
    EXPECT(status == 0, "minimal: exit status %d", status);
    EXPECT(out && strstr(out, "ray 4 ") && !strstr(out, "miss"), "minimal printed: %s",
           out ? out : "(nothing)");
    free(out);
}

static void test_raygen_deterministic(void)
{
    static const char *const kinds[] = {"camera", "random", "bounce"};
    tu_scene m = {0};
    size_t i;
    CHECK(write_lumpy_mesh(&m, "lumpy.obj"), "cannot write the test mesh");
    tu_scene_free(&m);
    for (i = 0; i < 3; i++) {
        unsigned char *a, *b, *c;
        size_t na = 0, nb = 0, nc = 0;
        int sa = tu_run("raygen @/lumpy.obj @/det_a.rays --kind %s --count 321 --seed 7", kinds[i]);
        int sb = tu_run("raygen @/lumpy.obj @/det_b.rays --seed 7 --count 321 --kind %s", kinds[i]);
        int sc = tu_run("raygen @/lumpy.obj @/det_c.rays --kind %s --count 321 --seed 8", kinds[i]);
        a = tu_slurp(tu_scratch("det_a.rays"), &na);
        b = tu_slurp(tu_scratch("det_b.rays"), &nb);
        c = tu_slurp(tu_scratch("det_c.rays"), &nc);
        EXPECT(sa == 0 && sb == 0 && sc == 0, "%s: exit status %d %d %d", kinds[i], sa, sb, sc);
        EXPECT(a && b && c && na == 321 * 32 && nb == na && nc == na,
               "%s: sizes %lu %lu %lu, expected %d", kinds[i], (unsigned long)na,
               (unsigned long)nb, (unsigned long)nc, 321 * 32);
        EXPECT(a && b && na == nb && memcmp(a, b, na) == 0, "%s: same seed, different bytes",
               kinds[i]);
        EXPECT(a && c && na == nc && memcmp(a, c, na) != 0, "%s: seeds 7 and 8 give the same rays",
               kinds[i]);
        free(a);
        free(b);
        free(c);
    }
}

/* The documented camera: one eye on the +z side of the box and above its
** centre, looking at the centre with a 45 degree field of view; ray i goes
** through pixel (i mod w, i div w) of a w x h grid, w = ceil(sqrt(count)),
** top row first, at a jittered point inside that pixel. */
static void test_raygen_camera(void)
{
    const double half = tan(22.5 * 3.14159265358979323846 / 180.0), eps = 1e-5;
    const int w = 32, h = 32;   /* for 1000 rays */
    tu_scene m = {0};
    brt_ray *rays = NULL;
    size_t count = 0, i;
    float bmin[3], bmax[3];
    double fwd[3], right[3], up[3], len;
    int k, status;
    CHECK(write_lumpy_mesh(&m, "lumpy.obj"), "cannot write the test mesh");
    tu_scene_bounds(&m, bmin, bmax);
    tu_scene_free(&m);
    status = tu_run("raygen @/lumpy.obj @/cam.rays --kind camera --count 1000");
    CHECK(status == 0, "raygen camera: exit status %d", status);
    rays = load_rays(tu_scratch("cam.rays"), &count);
    CHECK(rays && count == 1000, "expected 1000 camera rays, read %lu", (unsigned long)count);
    if (!rays_are_unit_and_unbounded(rays, count)) { free(rays); return; }
    EXPECT(rays[0].org[2] > bmax[2] && rays[0].org[1] > 0.5f * (bmin[1] + bmax[1]),
           "eye (%g, %g, %g) not in front of the box and above its centre", rays[0].org[0],
           rays[0].org[1], rays[0].org[2]);
    /* The camera frame: forward to the centre, right = forward x (0,1,0). */
    for (k = 0; k < 3; k++) fwd[k] = 0.5 * ((double)bmin[k] + bmax[k]) - rays[0].org[k];
    len = sqrt(fwd[0] * fwd[0] + fwd[1] * fwd[1] + fwd[2] * fwd[2]);
    for (k = 0; k < 3; k++) fwd[k] /= len;
    len = sqrt(fwd[0] * fwd[0] + fwd[2] * fwd[2]);
    right[0] = -fwd[2] / len; right[1] = 0; right[2] = fwd[0] / len;
    up[0] = right[1] * fwd[2] - right[2] * fwd[1];
    up[1] = right[2] * fwd[0] - right[0] * fwd[2];
    up[2] = right[0] * fwd[1] - right[1] * fwd[0];
    for (i = 0; i < count && !test_failed(); i++) {
        const float *d = rays[i].dir;
        double z = d[0] * fwd[0] + d[1] * fwd[1] + d[2] * fwd[2];
        double x = (d[0] * right[0] + d[1] * right[1] + d[2] * right[2]) / z / half;
        double y = (d[0] * up[0] + d[1] * up[1] + d[2] * up[2]) / z / half;
        double col = (x + 1) / 2 * w, row = (1 - y) / 2 * h;   /* pixel units */
        EXPECT(memcmp(rays[i].org, rays[0].org, sizeof rays[0].org) == 0,
               "ray %lu: a second eye", (unsigned long)i);
        EXPECT(col >= (double)(i % w) - eps && col <= (double)(i % w + 1) + eps
               && row >= (double)(i / w) - eps && row <= (double)(i / w + 1) + eps,
               "ray %lu goes through pixel (%.4f, %.4f), not (%lu, %lu)", (unsigned long)i, col,
               row, (unsigned long)(i % w), (unsigned long)(i / w));
        EXPECT(i == 0 || memcmp(rays[i].dir, rays[i - 1].dir, sizeof rays[i].dir) != 0,
               "rays %lu and %lu share a direction", (unsigned long)i - 1, (unsigned long)i);
    }
    free(rays);
}

static void test_raygen_random(void)
{
    brt_ray *rays;
    size_t count = 0, i;
    int k, status, negative[3] = {0, 0, 0}, positive[3] = {0, 0, 0};
    CHECK(write_cube("cube.obj"), "cannot write the cube");
    status = tu_run("raygen @/cube.obj @/random.rays --kind random --count 2000 --seed 3");
    CHECK(status == 0, "raygen random: exit status %d", status);
    rays = load_rays(tu_scratch("random.rays"), &count);
    CHECK(rays && count == 2000, "expected 2000 random rays, read %lu", (unsigned long)count);
    if (!rays_are_unit_and_unbounded(rays, count)) { free(rays); return; }
    for (i = 0; i < count; i++)
        for (k = 0; k < 3; k++) {
            /* The cube [-1,1]^3 grown by 10 %: [-1.1, 1.1]^3. */
            EXPECT(fabsf(rays[i].org[k]) <= 1.1f, "ray %lu: origin %g outside the grown box",
                   (unsigned long)i, rays[i].org[k]);
            negative[k] += rays[i].dir[k] < 0;
            positive[k] += rays[i].dir[k] > 0;
        }
    /* Uniform on the sphere: each half-space gets about half the rays
    ** (binomial sd 22; 300 rays off is 13 sd). */
    for (k = 0; k < 3; k++)
        EXPECT(abs(negative[k] - 1000) < 300 && abs(positive[k] - 1000) < 300,
               "axis %d: %d negative, %d positive directions", k, negative[k], positive[k]);
    free(rays);
}

/* Bounce rays on a convex body: each starts just outside a face and points
** away from it, so none may hit the cube again; the cosine weighting shows
** as a mean cosine of 2/3 to the face normal (a uniform hemisphere: 1/2). */
static void test_raygen_bounce(void)
{
    tu_scene cube = {0};
    brt_ray *rays;
    size_t count = 0, i;
    double cos_sum = 0;
    int status;
    make_cube(&cube);
    CHECK(write_obj(tu_scratch("cube.obj"), &cube), "cannot write the cube");
    status = tu_run("raygen @/cube.obj @/bounce.rays --kind bounce --count 4000 --seed 5");
    CHECK(status == 0, "raygen bounce: exit status %d", status);
    rays = load_rays(tu_scratch("bounce.rays"), &count);
    CHECK(rays && count == 4000, "expected 4000 bounce rays, read %lu", (unsigned long)count);
    if (!rays_are_unit_and_unbounded(rays, count)) { free(rays); return; }
    for (i = 0; i < count && !test_failed(); i++) {
        const brt_ray *r = &rays[i];
        brt_hit hit = brute_force_hit(&cube, r);
        int k, face = 0;
        for (k = 1; k < 3; k++)
            if (fabsf(r->org[k]) > fabsf(r->org[face])) face = k;
        /* Outside by a small relative epsilon (1e-5 of the scale here). */
        EXPECT(fabsf(r->org[face]) > 1.0f && fabsf(r->org[face]) < 1.0f + 1e-3f,
               "ray %lu: origin (%g, %g, %g) not just outside a face", (unsigned long)i,
               r->org[0], r->org[1], r->org[2]);
        EXPECT(r->dir[face] * r->org[face] > 0, "ray %lu: points into its face", (unsigned long)i);
        EXPECT(hit.prim == BRT_NO_PRIM, "ray %lu hits the cube again (prim %u, t %g)",
               (unsigned long)i, (unsigned)hit.prim, hit.t);
        cos_sum += fabsf(r->dir[face]);
    }
    EXPECT(fabs(cos_sum / (double)count - 2.0 / 3.0) < 0.03,
           "mean cosine to the normal %g, expected 2/3", cos_sum / (double)count);
    free(rays);
    tu_scene_free(&cube);
}

/* Rays of the test's own making that stress the ray interval: from a
** random point towards a random point near the centre (reached at t = 1,
** directions not normalised), with random tnear and tfar around 1, so
** that many hits lie just inside or outside [tnear, tfar] (some empty). */
static int write_interval_rays(const char *path, size_t count)
{
    uint64_t rng = test_seed() ^ 0x1234u;
    unsigned char *data = malloc(32 * count);
    size_t i;
    int k, ok;
    if (!data) return 0;
    for (i = 0; i < count; i++) {
        unsigned char *r = data + 32 * i;
        for (k = 0; k < 3; k++) {
            float from = tu_rnd(&rng, -2.5f, 2.5f), to = tu_rnd(&rng, -0.5f, 0.5f);
            put_f32(r + 4 * k, from);
            put_f32(r + 12 + 4 * k, to - from);
        }
        put_f32(r + 24, tu_rnd(&rng, 0.0f, 0.7f));
        put_f32(r + 28, tu_rnd(&rng, 0.3f, 1.3f));
    }
    ok = tu_spill(path, data, 32 * count);
    free(data);
    return ok;
}

/* Traces RAYS with build/trace and compares the hit file byte for byte
** with the brute-force oracle. */
static void expect_trace_matches_oracle(const tu_scene *m, const char *rays_name)
{
    brt_ray *rays;
    unsigned char *got, expected[16];
    size_t count = 0, size = 0, i, hits = 0;
    int status = tu_run("trace @/lumpy.obj @/%s @/trace.hits", rays_name);
    rays = load_rays(tu_scratch(rays_name), &count);
    got = tu_slurp(tu_scratch("trace.hits"), &size);
    EXPECT(status == 0, "%s: trace exit status %d", rays_name, status);
    EXPECT(rays && got && size == 16 * count, "%s: %lu hit bytes for %lu rays", rays_name,
           (unsigned long)size, (unsigned long)count);
    for (i = 0; rays && got && size == 16 * count && i < count; i++) {
        brt_hit hit = brute_force_hit(m, &rays[i]);
        put_f32(expected, hit.t);
        put_le32(expected + 4, hit.prim);
        put_f32(expected + 8, hit.u);
        put_f32(expected + 12, hit.v);
        hits += hit.prim != BRT_NO_PRIM;
        if (memcmp(got + 16 * i, expected, 16) != 0) {
            test_fail_at(__FILE__, __LINE__,
                         "%s ray %lu: trace t %.9g prim %u, oracle t %.9g prim %u",
                         rays_name, (unsigned long)i, get_f32(got + 16 * i),
                         (unsigned)get_le32(got + 16 * i + 4), hit.t, (unsigned)hit.prim);
            break;
        }
    }
    /* A comparison of misses alone would prove little (bounce rays leave
    ** the lumpy sphere mostly outwards: about 12 % hit). */
    EXPECT(hits > count / 20, "%s: only %lu of %lu rays hit", rays_name, (unsigned long)hits,
           (unsigned long)count);
    free(rays);
    free(got);
}

static void test_trace_equals_brute_force(void)
{
    static const char *const kinds[] = {"camera", "random", "bounce"};
    tu_scene m = {0};
    size_t i;
    CHECK(write_lumpy_mesh(&m, "lumpy.obj"), "cannot write the test mesh");
    for (i = 0; i < 3; i++) {
        char name[32];
        int status;
        snprintf(name, sizeof name, "%s.rays", kinds[i]);
        status = tu_run("raygen @/lumpy.obj @/%s --kind %s --count 1500 --seed %llu", name,
                     kinds[i], (unsigned long long)test_seed());
        EXPECT(status == 0, "raygen %s: exit status %d", kinds[i], status);
        expect_trace_matches_oracle(&m, name);
    }
    EXPECT(write_interval_rays(tu_scratch("interval.rays"), 1500), "cannot write rays");
    expect_trace_matches_oracle(&m, "interval.rays");
    tu_scene_free(&m);
}

/* The statistics of direct mode, and the summary line on stderr only when
** asked for (stderr is not a terminal under system()). */
static void test_trace_stats(void)
{
    char *json, *err;
    double seconds;
    int status;
    CHECK(write_cube("cube.obj"), "cannot write the cube");
    status = tu_run("raygen @/cube.obj @/stats.rays --kind camera --count 777");
    CHECK(status == 0, "raygen: exit status %d", status);
    status = tu_run("trace @/cube.obj @/stats.rays @/stats.hits --stats @/stats.json");
    err = tu_last_stderr();
    EXPECT(status == 0 && err && err[0] == 0, "trace --stats: exit status %d, stderr '%s'",
           status, err ? err : "(none)");
    free(err);
    json = (char *)tu_slurp(tu_scratch("stats.json"), NULL);
    CHECK(json, "no statistics file");
    /* timings: present (NAN when absent fails every compare), not
    ** negative, and the speed is the rays over the time (%.17g round-trips) */
    seconds = tu_json_number(json, "seconds");
    EXPECT(tu_json_number(json, "rays") == 777 && tu_json_number(json, "bvh_bytes_per_triangle") > 0
           && seconds >= 0 && tu_json_number(json, "build_seconds") >= 0
           && tu_json_number(json, "mrays_per_second") == (seconds > 0 ? 777 / seconds * 1e-6 : 0)
           && tu_json_number(json, "memory_limit") == 0 && tu_json_number(json, "batch_loads") == 0,
           "statistics of direct mode: %s", json);
    free(json);
    status = tu_run("trace @/cube.obj @/stats.rays @/stats.hits --verbose");
    err = tu_last_stderr();
    EXPECT(status == 0 && err && !strncmp(err, "trace: 777 rays, ", 17)
           && strstr(err, "Mrays/s\n") && strchr(err, '\n') == err + strlen(err) - 1,
           "--verbose: exit status %d, stderr '%s'", status, err ? err : "(none)");
    free(err);
}

/* trace --batched writes the bytes of --direct for any settings; the
** scene file is built once, reused, and rebuilt when a setting changes. */
static void test_trace_batched(void)
{
    static const char *const settings[] = {
        "--point-tris 1 --proxy-res 2 --memory 1K", "--point-tris 7 --proxy-res 16 --no-proxy",
        "--point-tris 1000 --proxy-res 256 --memory 64K", "--point-tris 40 --proxy-res 64 --memory 20K"};
    tu_scene m = {0};
    unsigned char *direct, *batched;
    size_t i, n_direct = 0, n_batched = 0;
    char *err, *json;
    int status;
    CHECK(write_lumpy_mesh(&m, "lumpy.obj"), "cannot write the test mesh");
    status = tu_run("raygen @/lumpy.obj @/batched.rays --kind bounce --count 3000");
    CHECK(status == 0, "raygen: exit status %d", status);
    CHECK(tu_run("trace @/lumpy.obj @/batched.rays @/direct.hits") == 0, "trace --direct failed");
    direct = tu_slurp(tu_scratch("direct.hits"), &n_direct);
    for (i = 0; i < sizeof settings / sizeof *settings; i++) {
        status = tu_run("trace @/lumpy.obj @/batched.rays @/batched.hits --batched --scene @/b.brs "
                     "--verbose --stats @/batched.json %s", settings[i]);
        err = tu_last_stderr();
        EXPECT(status == 0 && err && strstr(err, "(built)"), "'%s': exit %d, stderr '%s'",
               settings[i], status, err ? err : "");
        free(err);
        batched = tu_slurp(tu_scratch("batched.hits"), &n_batched);
        EXPECT(direct && batched && n_direct == n_batched && !memcmp(direct, batched, n_direct),
               "'%s': the batched hit file differs from the direct one", settings[i]);
        free(batched);
    }
    json = (char *)tu_slurp(tu_scratch("batched.json"), NULL);
    EXPECT(json && tu_json_number(json, "rays") == 3000 && tu_json_number(json, "batch_loads") > 0 &&
           tu_json_number(json, "disk_bytes_read") > 0 && tu_json_number(json, "queued_visits") > 0 &&
           tu_json_number(json, "proxy_tests") > 0 && tu_json_number(json, "memory_limit") == 20480 &&
           tu_json_number(json, "geometry_bytes") > 0 && tu_json_number(json, "proxy_bytes") > 0 &&
           tu_json_number(json, "cache_peak_bytes") > 0 && tu_json_number(json, "proxy_culled") > 0 &&
           tu_json_number(json, "proxy_culled") <= tu_json_number(json, "proxy_tests") &&
           tu_json_number(json, "batching_points") >= (double)m.tcount / 40.0,
           "batched statistics: %s", json ? json : "(none)");
    free(json);
    status = tu_run("trace @/lumpy.obj @/batched.rays @/batched.hits --batched --scene @/b.brs "
                 "--verbose %s", settings[3]);
    err = tu_last_stderr();
    EXPECT(status == 0 && err && strstr(err, "(reused)"), "same settings: stderr '%s'", err ? err : "");
    free(err);
    /* Without --scene the file goes to $BRT_SCENE_DIR. */
    setenv("BRT_SCENE_DIR", tu_scratch("scenes"), 1);
    status = tu_run("trace @/lumpy.obj @/batched.rays @/batched.hits --batched --point-tris 100");
    EXPECT(status == 0 && tu_file_exists(tu_scratch("scenes")), "default scene folder: exit %d", status);
    unsetenv("BRT_SCENE_DIR");
    free(direct);
    tu_scene_free(&m);
}

/* Rewrites record i of a hit file: prim and t as given. */
static int patch_hit(const char *path, size_t i, uint32_t prim, float t)
{
    size_t size;
    unsigned char *data = tu_slurp(path, &size);
    int ok = data && 16 * i + 16 <= size;
    if (ok) {
        put_f32(data + 16 * i, t);
        put_le32(data + 16 * i + 4, prim);
        ok = tu_spill(path, data, size);
    }
    free(data);
    return ok;
}

/* The first hit record of a hit file that is a hit, or -1. */
static long first_hit(const char *path, float *t, uint32_t *prim)
{
    size_t size, i;
    unsigned char *data = tu_slurp(path, &size);
    long found = -1;
    for (i = 0; data && found < 0 && 16 * i + 16 <= size; i++)
        if (get_le32(data + 16 * i + 4) != BRT_NO_PRIM) {
            found = (long)i;
            *t = get_f32(data + 16 * i);
            *prim = get_le32(data + 16 * i + 4);
        }
    free(data);
    return found;
}

static void expect_hitdiff(int expected_status, const char *expected_text, const char *options)
{
    int status = tu_run("hitdiff @/diff_a.hits @/diff_b.hits %s", options);
    char *out = tu_last_stdout();
    EXPECT(status == expected_status, "hitdiff %s: exit status %d, expected %d", options,
           status, expected_status);
    EXPECT(out && strstr(out, expected_text), "hitdiff %s: no '%s' in:\n%s", options,
           expected_text, out ? out : "(nothing)");
    free(out);
}

static void test_hitdiff(void)
{
    tu_scene m = {0};
    unsigned char *hits;
    size_t size = 0;
    float t = 0;
    uint32_t prim = 0;
    long i;
    int status;
    CHECK(write_lumpy_mesh(&m, "lumpy.obj"), "cannot write the test mesh");
    tu_scene_free(&m);
    status = tu_run("raygen @/lumpy.obj @/diff.rays --kind camera --count 1000");
    CHECK(status == 0, "raygen: exit status %d", status);
    status = tu_run("trace @/lumpy.obj @/diff.rays @/diff_a.hits");
    CHECK(status == 0, "trace: exit status %d", status);
    hits = tu_slurp(tu_scratch("diff_a.hits"), &size);
    CHECK(hits && size == 16000 && tu_spill(tu_scratch("diff_b.hits"), hits, size), "cannot copy hits");
    free(hits);
    expect_hitdiff(0, "AGREE: 0 of 1000 rays disagree", "");

    i = first_hit(tu_scratch("diff_a.hits"), &t, &prim);
    CHECK(i >= 0, "no camera ray hits the test mesh");
    /* The same prim, t off by 1e-3 relative: past the default --t-rel. */
    CHECK(patch_hit(tu_scratch("diff_b.hits"), (size_t)i, prim, t * 1.001f), "cannot patch");
    expect_hitdiff(1, "DISAGREE: 1 of 1000 rays disagree", "");
    expect_hitdiff(0, "AGREE: 0 of 1000", "--t-rel 0.01");
    /* Another prim: one disagreement whatever --t-rel, 0.1 % of the rays. */
    CHECK(patch_hit(tu_scratch("diff_b.hits"), (size_t)i, prim + 1, t), "cannot patch");
    expect_hitdiff(1, "DISAGREE: 1 of 1000", "--t-rel 0.5");
    expect_hitdiff(1, "DISAGREE: 1 of 1000", "--max-disagree 0.0009");
    expect_hitdiff(0, "AGREE: 1 of 1000", "--max-disagree 0.001");
    /* A miss in B where A hits. */
    CHECK(patch_hit(tu_scratch("diff_b.hits"), (size_t)i, BRT_NO_PRIM, INFINITY), "cannot patch");
    expect_hitdiff(1, "hit in A only                                 1", "");

    hits = tu_slurp(tu_scratch("diff_a.hits"), &size);
    CHECK(hits && tu_spill(tu_scratch("diff_b.hits"), hits, size - 16), "cannot shorten hits");
    free(hits);
    status = tu_run("hitdiff @/diff_a.hits @/diff_b.hits");
    hits = (unsigned char *)tu_last_stderr();
    EXPECT(status == 2, "lengths 1000 and 999: exit status %d, expected 2", status);
    EXPECT(hits && strstr((char *)hits, "hitdiff: ") && strstr((char *)hits, "999"),
           "no clear message on different lengths: %s", hits ? (char *)hits : "(nothing)");
    free(hits);
}

/* One bad invocation: the words its stderr line must contain and the
** output file it must not leave behind ('@' is the scratch directory). */
typedef struct bad_case {
    const char *args;
    const char *words;   /* program prefix and the place, e.g. "trace: ... --proxy-res" */
    const char *output;  /* NULL when the command names no output */
} bad_case;

static const bad_case bad_cases[] = {
    {"trace @/missing.obj @/good.rays @/bad1.hits", "missing.obj", "bad1.hits"},
    {"trace @/malformed.obj @/good.rays @/bad2.hits", "malformed.obj:4", "bad2.hits"},
    {"trace @/good.obj @/odd.rays @/bad3.hits", "odd.rays", "bad3.hits"},
    {"trace @/good.obj @/missing.rays @/bad4.hits", "missing.rays", "bad4.hits"},
    {"trace @/good.obj @/good.rays @/bad5.hits --frobnicate", "--frobnicate", "bad5.hits"},
    {"trace @/good.obj @/good.rays @/bad6.hits --proxy-res 3", "--proxy-res", "bad6.hits"},
    {"trace @/good.obj @/good.rays @/bad7.hits --proxy-res 2048", "--proxy-res", "bad7.hits"},
    {"trace @/good.obj @/good.rays @/bad8.hits --memory 0", "--memory", "bad8.hits"},
    {"trace @/good.obj @/good.rays @/bad9.hits --memory 12X", "--memory", "bad9.hits"},
    {"trace @/good.obj @/good.rays @/bad10.hits --point-tris 0", "--point-tris", "bad10.hits"},
    {"trace @/good.obj @/good.rays @/bad11.hits --proxy-res", "--proxy-res", "bad11.hits"},
    {"trace @/good.obj @/good.rays @/bad11.hits --batched --rays-in-flight 0", "--rays-in-flight", "bad11.hits"},
    {"trace @/good.obj @/good.rays", "HITS", NULL},
    {"trace @/good.obj @/good.rays @/no_such_dir/bad12.hits", "no_such_dir/bad12.hits", NULL},
    {"raygen @/missing.obj @/bad13.rays --kind camera", "missing.obj", "bad13.rays"},
    {"raygen @/malformed.obj @/bad14.rays --kind random", "malformed.obj:4", "bad14.rays"},
    {"raygen @/good.obj @/bad15.rays --kind camera --count 0", "--count", "bad15.rays"},
    {"raygen @/good.obj @/bad16.rays --kind camera --count -5", "--count", "bad16.rays"},
    {"raygen @/good.obj @/bad17.rays --kind sideways", "--kind", "bad17.rays"},
    {"raygen @/good.obj @/bad18.rays", "--kind", "bad18.rays"},
    {"raygen @/good.obj @/bad19.rays --kind", "--kind", "bad19.rays"},
    {"raygen @/good.obj @/bad20.rays --kind random --seed x1", "--seed", "bad20.rays"},
    {"raygen @/good.obj @/bad21.rays --kind random --fast", "--fast", "bad21.rays"},
    {"raygen @/empty.obj @/bad22.rays --kind camera", "empty.obj", "bad22.rays"},
    {"raygen @/edge_on.obj @/bad23.rays --kind bounce", "edge_on.obj", "bad23.rays"},
    {"trace @/good.obj @/good.rays @/bad24.hits --batched --scene @/corrupt.brs", "corrupt.brs: not a batchrt scene file", "bad24.hits"},
    {"trace @/good.obj @/good.rays @/bad25.hits --batched --scene @/short.brs", "short.brs: truncated", "bad25.hits"},
    {"trace @/missing.obj @/good.rays @/bad26.hits --batched --scene @/s26.brs", "missing.obj", "bad26.hits"},
    {"hitdiff @/missing.hits @/good.hits", "missing.hits", NULL},
    {"hitdiff @/good.hits @/odd.hits", "odd.hits", NULL},
    {"hitdiff @/good.hits @/good.hits --max-disagree 2", "--max-disagree", NULL},
    {"hitdiff @/good.hits @/good.hits --t-rel nan", "--t-rel", NULL},
    {"hitdiff @/good.hits --quiet @/good.hits", "--quiet", NULL},
    {"hitdiff @/good.hits", "B.hits", NULL},
};

static void test_bad_input(void)
{
    static const char malformed[] = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n";
    /* In the plane x = 0, which holds the camera: seen edge-on, never hit. */
    static const char edge_on[] = "v 0 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\n";
    unsigned char zeros[33], garbage[300];
    size_t i;
    int status;
    memset(zeros, 0, sizeof zeros);
    memset(garbage, 'x', sizeof garbage);
    CHECK(write_cube("good.obj") && tu_spill(tu_scratch("malformed.obj"), malformed,
          sizeof malformed - 1) && tu_spill(tu_scratch("empty.obj"), "", 0)
          && tu_spill(tu_scratch("edge_on.obj"), edge_on, sizeof edge_on - 1)
          && tu_spill(tu_scratch("odd.rays"), zeros, 33) && tu_spill(tu_scratch("odd.hits"), zeros, 17)
          && tu_spill(tu_scratch("corrupt.brs"), garbage, sizeof garbage)
          && tu_spill(tu_scratch("short.brs"), garbage, 100),
          "cannot write the inputs");
    status = tu_run("raygen @/good.obj @/good.rays --kind random --count 10");
    CHECK(status == 0, "raygen: exit status %d", status);
    status = tu_run("trace @/good.obj @/good.rays @/good.hits");
    CHECK(status == 0, "trace: exit status %d", status);
    for (i = 0; i < sizeof bad_cases / sizeof *bad_cases; i++) {
        const bad_case *c = &bad_cases[i];
        char prefix[16], *err;
        size_t len;
        status = tu_run("%s", c->args);
        err = tu_last_stderr();
        len = err ? strlen(err) : 0;
        snprintf(prefix, sizeof prefix, "%.*s: ", (int)strcspn(c->args, " "), c->args);
        EXPECT(status == 1, "'%s': exit status %d, expected 1", c->args, status);
        EXPECT(err && strncmp(err, prefix, strlen(prefix)) == 0 && strstr(err, c->words)
               && len > 0 && err[len - 1] == '\n' && strchr(err, '\n') == err + len - 1,
               "'%s': expected one line '%s...%s...', got '%s'", c->args, prefix, c->words,
               err ? err : "(nothing)");
        EXPECT(!c->output || !tu_file_exists(tu_scratch(c->output)), "'%s' left %s behind", c->args,
               c->output);
        EXPECT(!tu_temporary_file_left(), "'%s' left a temporary file behind", c->args);
        free(err);
    }
}

/* ===================================================================== */
/* PNG: an independent decoder for the stored-block subset               */
/* ===================================================================== */

/* Decodes png and compares it with the w x h RGB image; 1 when equal. */
static int png_decodes_to(const unsigned char *png, size_t size, int w, int h,
                          const unsigned char *rgb)
{
    int dw = 0, dh = 0;
    unsigned char *pixels = tu_png_decode(png, size, &dw, &dh);
    int ok = pixels && dw == w && dh == h && !memcmp(pixels, rgb, 3 * (size_t)w * (size_t)h);
    free(pixels);
    return ok;
}

static void test_png(void)
{
    /* 1x1, scanlines that fill one stored block exactly (15 x 4369 bytes
    ** = 65535), one byte more, and an image over several blocks. */
    static const int sizes[][2] = {{1, 1}, {17, 5}, {1456, 15}, {21845, 1}, {300, 200}};
    uint64_t rng = test_seed();
    size_t i, j;
    EXPECT(ex_crc32((const unsigned char *)"123456789", 9) == 0xCBF43926u, "CRC-32 check value");
    EXPECT(ex_adler32((const unsigned char *)"Wikipedia", 9) == 0x11E60398u,
           "Adler-32 check value");
    for (i = 0; i < sizeof sizes / sizeof *sizes; i++) {
        int w = sizes[i][0], h = sizes[i][1];
        size_t n = 3 * (size_t)w * (size_t)h, png_size = 0;
        unsigned char *rgb = malloc(n), *png = NULL;
        CHECK(rgb, "out of memory");
        for (j = 0; j < n; j++) rgb[j] = (unsigned char)brt_random_u64(&rng);
        EXPECT(ex_png_encode_rgb(w, h, rgb, &png, &png_size) == BRT_OK, "%dx%d: encode failed",
               w, h);
        EXPECT(png && png_decodes_to(png, png_size, w, h, rgb), "%dx%d: the PNG does not decode "
               "to the image", w, h);
        EXPECT(ex_crc32(rgb, n) == tu_crc32_bitwise(rgb, n)
               && ex_adler32(rgb, n) == tu_adler32_slow(rgb, n),
               "%dx%d: checksums differ from the definitions", w, h);
        free(rgb);
        free(png);
    }
}

static void test_png_write(void)
{
    static const unsigned char rgb[2 * 2 * 3] = {255, 0, 0, 0, 255, 0, 0, 0, 255, 9, 9, 9};
    brt_error err;
    unsigned char *png;
    size_t size = 0;
    EXPECT(ex_png_write_rgb(tu_scratch("tiny.png"), 2, 2, rgb, &err) == BRT_OK, "%s", err.message);
    png = tu_slurp(tu_scratch("tiny.png"), &size);
    EXPECT(png && png_decodes_to(png, size, 2, 2, rgb), "tiny.png does not decode");
    EXPECT(ex_png_write_rgb(tu_scratch("no_such_dir/x.png"), 2, 2, rgb, &err) != BRT_OK
           && strstr(err.message, "no_such_dir/x.png"), "writing into a missing folder: '%s'",
           err.message);
    free(png);
    EXPECT(ex_png_encode_rgb(0, 5, rgb, &png, &size) == BRT_EARG && !png,
           "a 0x5 image was accepted");
}

/* ===================================================================== */
/* Out of core from end to end                                           */
/* ===================================================================== */

/* Overwrites a file in place with garbage of the same size and puts its
** times back: size, modification time and inode -- the stamp of
** brt_scene_source_stamp -- stay, the contents do not parse. */
static int garble_keeping_stamp(const char *path)
{
    struct stat st;
    struct timespec times[2];
    char junk[4096];
    off_t done = 0;
    int fd = open(path, O_WRONLY), ok;
    if (fd < 0 || fstat(fd, &st) != 0) return 0;
    memset(junk, '#', sizeof junk);
    junk[0] = 'x';   /* not a comment: the first line is an unknown statement... */
    memcpy(junk + 1, " y\nf 9 9 9\n", 11);   /* ...then a face without vertices */
    while (done < st.st_size) {
        size_t n = st.st_size - done < (off_t)sizeof junk ? (size_t)(st.st_size - done) : sizeof junk;
        if (write(fd, junk, n) != (ssize_t)n) break;
        done += (off_t)n;
    }
    ok = close(fd) == 0 && done == st.st_size;
    times[0] = st.st_atim;
    times[1] = st.st_mtim;
    return ok && utimensat(AT_FDCWD, path, times, 0) == 0;
}

/* The stamp that tells a stale scene file (brt_scene_source_stamp) sees
** each of its parts alone: the modification time's nanoseconds and its
** seconds, the size, and the inode (a file replaced by rename, same size
** and times).  A part it missed would reuse an old scene file for a
** changed mesh. */
static void test_source_stamp_parts(void)
{
    const char *path = tu_put("stamp.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
    struct timespec times[2];
    uint64_t base, now;
    brt_error err;
    times[0].tv_sec = times[1].tv_sec = 1700000000;
    times[0].tv_nsec = times[1].tv_nsec = 100000000;
    CHECK(utimensat(AT_FDCWD, path, times, 0) == 0, "utimensat: %s", strerror(errno));
    CHECK(brt_scene_source_stamp(path, &base, &err) == BRT_OK, "%s", err.message);
    CHECK(brt_scene_source_stamp(path, &now, &err) == BRT_OK && now == base, "the same file, another stamp");
    times[1].tv_nsec = 200000000;   /* the same second */
    CHECK(utimensat(AT_FDCWD, path, times, 0) == 0, "utimensat: %s", strerror(errno));
    CHECK(brt_scene_source_stamp(path, &now, &err) == BRT_OK, "%s", err.message);
    EXPECT(now != base, "the stamp misses the modification time's nanoseconds");
    times[1].tv_sec++;
    times[1].tv_nsec = 100000000;   /* a second later, the same nanoseconds */
    CHECK(utimensat(AT_FDCWD, path, times, 0) == 0, "utimensat: %s", strerror(errno));
    CHECK(brt_scene_source_stamp(path, &now, &err) == BRT_OK, "%s", err.message);
    EXPECT(now != base, "the stamp misses the modification time's seconds");
    /* one byte more, the times put back */
    tu_put("stamp.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n\n");
    times[1].tv_sec--;
    CHECK(utimensat(AT_FDCWD, path, times, 0) == 0, "utimensat: %s", strerror(errno));
    CHECK(brt_scene_source_stamp(path, &now, &err) == BRT_OK, "%s", err.message);
    EXPECT(now != base, "the stamp misses the size");
    /* the same bytes and times in a new file renamed over it: a new inode */
    tu_put("stamp.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
    CHECK(utimensat(AT_FDCWD, path, times, 0) == 0, "utimensat: %s", strerror(errno));
    CHECK(brt_scene_source_stamp(path, &now, &err) == BRT_OK && now == base, "size and times put back, but "
          "another stamp");
    tu_put("stamp-new.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
    CHECK(utimensat(AT_FDCWD, tu_scratch("stamp-new.obj"), times, 0) == 0 &&
          rename(tu_scratch("stamp-new.obj"), path) == 0, "cannot replace the file");
    CHECK(brt_scene_source_stamp(path, &now, &err) == BRT_OK, "%s", err.message);
    EXPECT(now != base, "the stamp misses the inode (a file replaced by rename)");
}

/* Batched runs need the mesh only to build the scene file: once it
** exists and matches, trace --batched and render (camera, bounds,
** triangle count from the scene file) give the same bytes with the mesh
** file turned to garbage, which --direct then refuses. */
static void test_batched_needs_no_mesh(void)
{
    const char *render = "render @/nomesh.ply --scene @/nomesh-r.brs --point-tris 500 --width 24 "
                         "--height 16 --spp 2";
    char *err;
    int status;
    CHECK(tu_run("mkscene crown @/nomesh.ply --scale 0.05") == 0, "mkscene failed");
    CHECK(tu_run("raygen @/nomesh.ply @/nomesh.rays --kind bounce --count 2000") == 0, "raygen failed");
    CHECK(tu_run("trace @/nomesh.ply @/nomesh.rays @/nomesh-direct.hits") == 0, "trace failed");
    CHECK(tu_run("trace @/nomesh.ply @/nomesh.rays @/nomesh-built.hits --batched --point-tris 500 "
                 "--scene @/nomesh.brs") == 0, "trace --batched failed");
    CHECK(tu_run("%s --out @/nomesh-built.png", render) == 0, "render failed");
    CHECK(garble_keeping_stamp(tu_scratch("nomesh.ply")), "cannot garble the mesh");
    status = tu_run("trace @/nomesh.ply @/nomesh.rays @/nomesh-reused.hits --batched "
                    "--point-tris 500 --scene @/nomesh.brs --verbose");
    err = tu_last_stderr();
    EXPECT(status == 0 && err && strstr(err, "(reused)"), "trace --batched on the garbled mesh: "
           "exit %d, stderr '%s'", status, err ? err : "");
    free(err);
    EXPECT(tu_same_file_bytes(tu_scratch("nomesh-direct.hits"), tu_scratch("nomesh-reused.hits")),
           "trace --batched from the scene file alone differs from --direct");
    status = tu_run("%s --out @/nomesh-reused.png", render);
    err = tu_last_stderr();
    EXPECT(status == 0 && tu_same_file_bytes(tu_scratch("nomesh-built.png"),
                                          tu_scratch("nomesh-reused.png")),
           "render from the scene file alone: exit %d, stderr '%s', same image %d", status,
           err ? err : "", tu_same_file_bytes(tu_scratch("nomesh-built.png"), tu_scratch("nomesh-reused.png")));
    free(err);
    EXPECT(tu_run("trace @/nomesh.ply @/nomesh.rays @/nomesh-bad.hits") == 1,
           "trace --direct accepted the garbled mesh: the test proves nothing");
}

/* --direct holds the whole mesh: when it is larger than the --memory given,
** trace and render say so in one line and go on (exit 0, same hits). */
static void test_direct_notes_memory(void)
{
    static const char *const runs[] = {
        "trace @/note.ply @/note.rays @/note.hits --memory 1K",
        "render @/note.ply --direct --memory 1K --width 8 --height 8 --spp 1 --out @/note.png",
        "trace @/note.ply @/note.rays @/note.hits --memory 1G",   /* fits: no note */
    };
    size_t i;
    CHECK(tu_run("mkscene crown @/note.ply --scale 0.01") == 0, "mkscene failed");
    CHECK(tu_run("raygen @/note.ply @/note.rays --kind random --count 10") == 0, "raygen failed");
    for (i = 0; i < 3; i++) {
        int status = tu_run("%s", runs[i]);
        char *err = tu_last_stderr();
        int noted = err && strstr(err, "note: the direct run holds the whole mesh in memory")
                    && strchr(err, '\n') == err + strlen(err) - 1;
        EXPECT(status == 0 && (i < 2 ? noted : err && err[0] == 0),
               "'%s': exit %d, stderr '%s'", runs[i], status, err ? err : "(none)");
        free(err);
    }
}

/* Every program's statistics carry the process's peak resident memory. */
static void test_peak_rss_in_statistics(void)
{
    static const char *const runs[][2] = {
        {"trace @/rss.ply @/rss.rays @/rss.hits --stats @/rss-trace.json", "rss-trace.json"},
        {"trace @/rss.ply @/rss.rays @/rss.hits --batched --scene @/rss.brs --stats @/rss-tb.json",
         "rss-tb.json"},
        {"voxelize @/rss.ply --proxy-res 16 --stats @/rss-vox.json", "rss-vox.json"},
        {"render crown --scale 0.01 --width 8 --height 8 --spp 1 --direct --out @/rss.png "
         "--stats @/rss-rd.json", "rss-rd.json"},
        {"render crown --scale 0.01 --width 8 --height 8 --spp 1 --scene @/rss-r.brs --out @/rss.png "
         "--stats @/rss-rb.json", "rss-rb.json"},
        {"render crown --scale 0.01 --width 8 --height 8 --spp 1 --scene @/rss-r.brs --compare "
         "--out @/rss.png --stats @/rss-rc.json", "rss-rc-noproxy.json"},
    };
    size_t i;
    CHECK(tu_run("mkscene island @/rss.ply --scale 0.01") == 0, "mkscene failed");
    CHECK(tu_run("raygen @/rss.ply @/rss.rays --kind random --count 100") == 0, "raygen failed");
    for (i = 0; i < sizeof runs / sizeof *runs; i++) {
        char *json;
        int status = tu_run("%s", runs[i][0]);
        json = (char *)tu_slurp(tu_scratch(runs[i][1]), NULL);
        EXPECT(status == 0 && json && tu_json_number(json, "peak_rss_bytes") > 0,
               "'%s': exit %d, peak_rss_bytes %g", runs[i][0], status,
               json ? tu_json_number(json, "peak_rss_bytes") : NAN);
        free(json);
    }
}

/* ---- signals ---- */

/* Starts $BRT_BUILD/ARGV[0] with stdout and stderr to files in the
** scratch directory; returns the pid (or -1). */
static pid_t spawn(const char *const *argv, const char *err_name)
{
    char path[1024];
    const char *build = getenv("BRT_BUILD");
    pid_t pid;
    snprintf(path, sizeof path, "%s/%s", build ? build : "build", argv[0]);
    pid = fork();
    if (pid == 0) {
        int out = open(tu_scratch("spawn.out"), O_WRONLY | O_CREAT | O_TRUNC, 0644);
        int err = open(tu_scratch(err_name), O_WRONLY | O_CREAT | O_TRUNC, 0644);
        if (out < 0 || err < 0 || dup2(out, 1) < 0 || dup2(err, 2) < 0) _exit(127);
        execv(path, (char *const *)argv);   /* execv does not change them */
        _exit(127);
    }
    return pid;
}

/* Runs a program in DIR, sends it signo once a file has appeared there
** (or after max_wait_ms), and checks: it was still running, it exits with
** 128 + signo and one line "PROG: interrupted by SIG...", and DIR then
** holds nothing but `allowed` (a complete output, or NULL: nothing). */
static void check_interrupted(const char *const *argv, const char *dir, int signo, long max_wait_ms,
                              const char *allowed)
{
    char left[256] = "", *err;
    long waited = 0;
    int status = 0, entries;
    pid_t pid;
    CHECK(mkdir(dir, 0755) == 0 || errno == EEXIST, "cannot create %s", dir);
    pid = spawn(argv, "spawn.err");
    CHECK(pid > 0, "cannot start %s", argv[0]);
    while (waited < max_wait_ms && tu_dir_entries(dir, NULL, NULL, NULL, 0) == 0) {
        tu_sleep_ms(10);
        waited += 10;
    }
    /* Well into the writing, and past the program's start: a signal before
    ** it installs its handlers ends it as the default action does (a
    ** start slowed by the sanitizers, or by the other tests the runner
    ** runs beside this one).  Each program here works for seconds. */
    tu_sleep_ms(300);
    EXPECT(waitpid(pid, &status, WNOHANG) == 0, "%s finished before the signal", argv[0]);
    kill(pid, signo);
    CHECK(waitpid(pid, &status, 0) == pid, "waitpid failed");
    err = (char *)tu_slurp(tu_scratch("spawn.err"), NULL);
    EXPECT(WIFEXITED(status) && WEXITSTATUS(status) == 128 + signo && err
           && strstr(err, "interrupted by SIG") && strchr(err, '\n') == err + strlen(err) - 1,
           "%s after signal %d: status %#x, stderr '%s'", argv[0], signo, (unsigned)status,
           err ? err : "(none)");
    free(err);
    entries = tu_dir_entries(dir, NULL, NULL, left, sizeof left);
    EXPECT(entries == 0 || (entries == 1 && allowed && strcmp(left, allowed) == 0),
           "%s left %d files in %s after signal %d, e.g. '%s'", argv[0], entries, dir, signo, left);
}

/* mkscene and render (while it builds the scene file) stop on SIGTERM
** and SIGINT, remove their temporary files and write no output.  The
** landscape at scale 3 (25 M triangles baked) would take mkscene seconds, and render's build of scale 10 about one:
** the signal comes long before.  Should the build be done already, the
** render of 4 M paths that follows is not, and stops as well. */
static void test_interrupts_leave_nothing(void)
{
    char mk_dir[512], mk_out[600], r_dir[512], r_scene[600], r_out[600];
    const char *mkscene[] = {"mkscene", "landscape", mk_out, "--scale", "3", NULL};   /* then island, pbrt */
    const char *render[] = {"render", "landscape", "--scale", "10", "--proxy-res", "16", "--width", "320",
                            "--height", "200", "--spp", "64", "--scene", r_scene, "--out", r_out,
                            NULL};
    snprintf(mk_dir, sizeof mk_dir, "%s", tu_scratch("mkscene-interrupted"));
    snprintf(mk_out, sizeof mk_out, "%s/big.ply", mk_dir);
    check_interrupted(mkscene, mk_dir, SIGTERM, 10000, NULL);
    /* the pbrt writer (the instanced scenes' own path) too: seconds of output */
    snprintf(mk_out, sizeof mk_out, "%s/big.pbrt", mk_dir);
    mkscene[1] = "island";
    mkscene[4] = "20";
    check_interrupted(mkscene, mk_dir, SIGINT, 10000, NULL);
    snprintf(r_dir, sizeof r_dir, "%s", tu_scratch("render-interrupted"));
    snprintf(r_scene, sizeof r_scene, "%s/scene.brs", r_dir);
    snprintf(r_out, sizeof r_out, "%s/image.png", r_dir);
    /* A build that has already finished leaves its (complete) scene file. */
    check_interrupted(render, r_dir, SIGINT, 500, "scene.brs");
}

/* The other phases: render while it traces paths (batched, and --direct
** in memory) and trace --batched while it traces rays, each from a scene
** file built beforehand (so the program is tracing from its first
** milliseconds, for seconds), stop on SIGINT and SIGTERM with no output:
** the scene file alone stays. */
static void test_interrupts_while_tracing(void)
{
    char dir[512], scene[600], out[600], tdir[512], tscene[600], tout[600], mesh[600], rays[600];
    const char *render[] = {"render", "landscape", "--scale", "10", "--proxy-res", "16", "--width", "320",
                            "--height", "200", "--spp", "64", "--memory", "10%", "--threads", "1",
                            "--scene", scene, "--out", out, NULL};
    const char *direct[] = {"render", "landscape", "--scale", "10", "--width", "320", "--height", "200",
                            "--spp", "64", "--direct", "--threads", "1", "--out", out, NULL};
    const char *trace[] = {"trace", mesh, rays, tout, "--batched", "--memory", "1M", "--threads", "1",
                           "--scene", tscene, NULL};
    snprintf(dir, sizeof dir, "%s", tu_scratch("render-tracing"));
    snprintf(scene, sizeof scene, "%s/scene.brs", dir);
    snprintf(out, sizeof out, "%s/out.png", dir);
    CHECK(mkdir(dir, 0755) == 0, "cannot create %s", dir);
    CHECK(tu_run("render landscape --scale 10 --proxy-res 16 --width 8 --height 8 --spp 1 --scene %s --out %s",
                 scene, out) == 0 && unlink(out) == 0, "could not build the render's scene file");
    check_interrupted(render, dir, SIGINT, 0, "scene.brs");
    check_interrupted(render, dir, SIGTERM, 0, "scene.brs");
    check_interrupted(direct, dir, SIGINT, 0, "scene.brs");
    snprintf(tdir, sizeof tdir, "%s", tu_scratch("trace-tracing"));
    snprintf(tscene, sizeof tscene, "%s/scene.brs", tdir);
    snprintf(tout, sizeof tout, "%s/out.hits", tdir);
    snprintf(mesh, sizeof mesh, "%s", tu_scratch("interrupt.ply"));
    snprintf(rays, sizeof rays, "%s", tu_scratch("interrupt.rays"));
    CHECK(mkdir(tdir, 0755) == 0, "cannot create %s", tdir);
    CHECK(tu_run("mkscene landscape %s --scale 0.15625", mesh) == 0 &&
          tu_run("raygen %s %s --kind bounce --count 4000000", mesh, rays) == 0 &&
          tu_run("trace %s %s %s --batched --scene %s", mesh, rays, tout, tscene) == 0 && unlink(tout) == 0,
          "could not make the trace's mesh, rays and scene file");
    check_interrupted(trace, tdir, SIGINT, 0, "scene.brs");
    check_interrupted(trace, tdir, SIGTERM, 0, "scene.brs");
}

/* Ctrl-C at a terminal signals the whole foreground process group: the
** gzip that unpacks a pbrt scene's "*.ply.gz" dies of it too, and the
** program's build fails.  Every program that reads pbrt-v4 must still say
** "interrupted" and exit 130, not blame the file (ex_check), and leave
** neither output nor unpacked copy.  A stand-in gzip on the PATH
** announces itself and sleeps, so the signal always comes while it runs. */
static void check_group_interrupted(const char *const *argv, const char *bin, const char *tmp,
                                    const char *mark, const char *out)
{
    char path[1024], *err;
    const char *build = getenv("BRT_BUILD");
    long waited = 0;
    int status = 0;
    pid_t pid;
    unlink(mark);
    snprintf(path, sizeof path, "%s/%s", build ? build : "build", argv[0]);
    pid = fork();
    if (pid == 0) {
        char search[4096];
        int err_fd = open(tu_scratch("group.err"), O_WRONLY | O_CREAT | O_TRUNC, 0644);
        snprintf(search, sizeof search, "%s:%s", bin, getenv("PATH") ? getenv("PATH") : "/bin:/usr/bin");
        if (setpgid(0, 0) != 0 || err_fd < 0 || dup2(err_fd, 2) < 0 || setenv("PATH", search, 1) != 0 ||
            setenv("TMPDIR", tmp, 1) != 0 || setenv("BRT_TEST_MARK", mark, 1) != 0)
            _exit(127);
        execv(path, (char *const *)argv);
        _exit(127);
    }
    CHECK(pid > 0, "cannot start %s", argv[0]);
    setpgid(pid, pid);   /* either side may come first */
    while (waited < 60000 && !tu_file_exists(mark) && waitpid(pid, &status, WNOHANG) == 0) {
        tu_sleep_ms(10);
        waited += 10;
    }
    EXPECT(tu_file_exists(mark), "%s never started gzip", argv[0]);
    kill(-pid, SIGINT);
    CHECK(waitpid(pid, &status, 0) == pid, "waitpid failed");
    err = (char *)tu_slurp(tu_scratch("group.err"), NULL);
    EXPECT(WIFEXITED(status) && WEXITSTATUS(status) == 130 && err && strstr(err, "interrupted by SIGINT") &&
           strchr(err, '\n') == err + strlen(err) - 1,
           "%s, Ctrl-C while gzip runs: status %#x, stderr '%s'", argv[0], (unsigned)status, err ? err : "(none)");
    free(err);
    EXPECT(tu_dir_entries(tmp, NULL, NULL, NULL, 0) == 0, "%s left its unpacked copy in $TMPDIR", argv[0]);
    EXPECT(!out || !tu_file_exists(out), "%s wrote %s", argv[0], out);
}

/* Every program that reads pbrt-v4, Ctrl-C'd while the gzip that GZIP
** (a script) stands in for runs, on SCENE (a pbrt file whose mesh is
** "*.ply.gz"); PREFIX names the runs' files apart. */
static void interrupt_every_reader(const char *gzip, const char *scene, const char *prefix)
{
    char rays[600], hits[600], out[600], brs[600], bin[512], tmp[512], mark[512], name[64];
    const char *render[] = {"render", scene, "--direct", "--width", "8", "--height", "8", "--spp", "1",
                            "--out", out, NULL};
    const char *direct[] = {"trace", scene, rays, out, "--direct", NULL};
    const char *batched[] = {"trace", scene, rays, out, "--batched", "--scene", brs, NULL};
    const char *raygen[] = {"raygen", scene, out, "--kind", "random", NULL};
    const char *voxelize[] = {"voxelize", scene, "--out", out, NULL};
    const char *hitdiff[] = {"hitdiff", hits, hits, "--mesh", scene, "--rays", rays, "--explain", out, NULL};
    snprintf(name, sizeof name, "%s-bin/gzip", prefix);
    snprintf(bin, sizeof bin, "%s", tu_put(name, gzip));
    CHECK(chmod(bin, 0755) == 0, "cannot make %s executable", bin);
    *strrchr(bin, '/') = 0;
    snprintf(name, sizeof name, "%s-tmp", prefix);
    snprintf(tmp, sizeof tmp, "%s", tu_scratch(name));
    CHECK(mkdir(tmp, 0755) == 0, "cannot create %s", tmp);
    snprintf(name, sizeof name, "%s-started", prefix);
    snprintf(mark, sizeof mark, "%s", tu_scratch(name));
    snprintf(rays, sizeof rays, "%s", tu_scratch("gzip.rays"));
    snprintf(out, sizeof out, "%s", tu_scratch("gzip.out"));
    snprintf(brs, sizeof brs, "%s", tu_scratch("gzip.brs"));
    snprintf(hits, sizeof hits, "%s", tu_scratch("gzip.hits"));
    check_group_interrupted(render, bin, tmp, mark, out);
    check_group_interrupted(direct, bin, tmp, mark, out);
    check_group_interrupted(batched, bin, tmp, mark, out);
    EXPECT(!tu_file_exists(brs) && !tu_temporary_file_left(), "trace --batched left its scene file");
    check_group_interrupted(raygen, bin, tmp, mark, out);
    check_group_interrupted(voxelize, bin, tmp, mark, out);
    check_group_interrupted(hitdiff, bin, tmp, mark, out);
}

static int make_gzip_rays_and_hits(void)
{
    return tu_run("mkscene crown @/gzip-crown.ply --scale 0.01") == 0 &&
           tu_run("raygen @/gzip-crown.ply @/gzip.rays --kind random --count 100") == 0 &&
           tu_run("trace @/gzip-crown.ply @/gzip.rays @/gzip.hits") == 0;
}

/* The stand-in gzip dies of the Ctrl-C: the load fails, and the failure
** must be reported as the interrupt. */
static void test_ctrl_c_while_gzip_unpacks(void)
{
    CHECK(make_gzip_rays_and_hits(), "cannot make rays and hits");
    tu_put("gzip-scene/mesh.ply.gz", "not unpacked: the stand-in gzip never reads it\n");
    interrupt_every_reader("#!/bin/sh\n: > \"$BRT_TEST_MARK\"\nexec sleep 30\n",
                           tu_put("gzip-scene/scene.pbrt", "WorldBegin\nShape \"plymesh\" \"string filename\" "
                                  "\"mesh.ply.gz\"\n"), "gzip");
}

/* The stand-in gzip ignores the Ctrl-C and unpacks the mesh: the load
** succeeds with the interrupt pending, and the program's next poll (the
** build, the trace, hitdiff's referee before its first ray) must stop it
** and leave no output, not even a complete-looking one. */
static void test_ctrl_c_while_deaf_gzip_unpacks(void)
{
    char gzip[1024], real[600] = "";
    FILE *f = popen("command -v gzip", "r");
    CHECK(f && fgets(real, sizeof real, f) && real[0] == '/', "no gzip on the PATH");
    pclose(f);
    real[strcspn(real, "\n")] = 0;
    snprintf(gzip, sizeof gzip, "#!/bin/sh\ntrap '' INT\n: > \"$BRT_TEST_MARK\"\nsleep 1\nexec %s \"$@\"\n", real);
    CHECK(make_gzip_rays_and_hits(), "cannot make rays and hits");
    CHECK(mkdir(tu_scratch("deaf-scene"), 0755) == 0 &&
          tu_shell("gzip -c ", "@/gzip-crown.ply > @/deaf-scene/mesh.ply.gz", "") == 0, "cannot gzip the mesh");
    interrupt_every_reader(gzip, tu_put("deaf-scene/scene.pbrt", "WorldBegin\nShape \"plymesh\" \"string filename\" "
                                        "\"mesh.ply.gz\"\n"), "deaf");
}

/* One run of hitdiff --explain into DIR/ex.csv, SIGINT as soon as its
** temporary CSV appears (the referee loop has begun); the exit status
** (-1: it ended before the signal could land). */
static int hitdiff_interrupted_while_refereeing(const char *dir)
{
    char csv[700], hits_a[600], hits_b[600], mesh[600], rays[600], path[600];
    const char *build = getenv("BRT_BUILD");
    int status = 0, temporary = 0;
    long waited = 0;
    pid_t pid;
    snprintf(csv, sizeof csv, "%s/ex.csv", dir);
    snprintf(hits_a, sizeof hits_a, "%s", tu_scratch("hx-a.hits"));
    snprintf(hits_b, sizeof hits_b, "%s", tu_scratch("hx-b.hits"));
    snprintf(mesh, sizeof mesh, "%s", tu_scratch("hx.ply"));
    snprintf(rays, sizeof rays, "%s", tu_scratch("hx.rays"));
    snprintf(path, sizeof path, "%s/hitdiff", build ? build : "build");
    pid = fork();
    if (pid == 0) {
        int null = open("/dev/null", O_WRONLY);
        if (null >= 0) { dup2(null, 1); dup2(null, 2); }
        execl(path, "hitdiff", hits_a, hits_b, "--mesh", mesh, "--rays", rays, "--explain", csv, (char *)NULL);
        _exit(127);
    }
    if (pid < 0) return -2;
    while (waited < 60000 && (tu_dir_entries(dir, ".tmp.", &temporary, NULL, 0), temporary == 0) &&
           waitpid(pid, &status, WNOHANG) == 0) {
        tu_sleep_ms(1);
        waited++;
    }
    if (temporary == 0) {   /* it ended (or never began) before the referee's file */
        waitpid(pid, &status, 0);
        return -1;
    }
    kill(pid, SIGINT);
    if (waitpid(pid, &status, 0) != pid || !WIFEXITED(status)) return -2;
    return WEXITSTATUS(status) == 130 ? 130 : -1;
}

/* Ctrl-C while hitdiff referees: the CSV written so far is removed, not
** renamed into place looking whole (exit 130).  The referee must be
** caught in its loop: some 100,000 disagreeing rays (every hit's t
** moved by 1 %) take it about a second; a run that ends first is
** repeated, twice. */
static void test_hitdiff_interrupted_explain(void)
{
    unsigned char *hits;
    size_t size = 0, i;
    char dir[600];
    int status = -1, attempt;
    CHECK(tu_run("mkscene crown @/hx.ply --scale 0.05") == 0 &&
          tu_run("raygen @/hx.ply @/hx.rays --kind random --count 600000") == 0 &&
          tu_run("trace @/hx.ply @/hx.rays @/hx-a.hits") == 0, "cannot make the mesh, rays and hits");
    CHECK((hits = tu_slurp(tu_scratch("hx-a.hits"), &size)) != NULL, "cannot read the hits");
    for (i = 0; i + 16 <= size; i += 16) {
        float t;
        memcpy(&t, hits + i, 4);
        if (isfinite(t)) t *= 1.01f;
        memcpy(hits + i, &t, 4);
    }
    CHECK(tu_spill(tu_scratch("hx-b.hits"), hits, size), "cannot write the moved hits");
    free(hits);
    snprintf(dir, sizeof dir, "%s", tu_scratch("hx-dir"));
    CHECK(mkdir(dir, 0755) == 0, "cannot create %s", dir);
    for (attempt = 0; attempt < 3 && status == -1; attempt++) {
        char csv[700];
        snprintf(csv, sizeof csv, "%s/ex.csv", dir);
        unlink(csv);
        status = hitdiff_interrupted_while_refereeing(dir);
    }
    if (status == -1) {
        test_skip("hitdiff ended before the signal, three times: the machine is too fast for 600,000 rays");
        return;
    }
    CHECK(status == 130, "hitdiff, interrupted while refereeing: not exit 130 (%d)", status);
    EXPECT(tu_dir_entries(dir, NULL, NULL, NULL, 0) == 0, "hitdiff left its --explain CSV (or its temporary) "
           "after the interrupt");
}

/* trace --batched writes the bytes of --direct on every built-in scene,
** from a scene file built as a stream from mkscene's file (PLY and OBJ),
** each of 5 to 8 thousand triangles. */
static void test_builtin_scenes_batched_equals_direct(void)
{
    static const char *const files[] = {"crown.ply", "landscape.ply", "island.obj"};
    static const char *const scales[] = {"0.05", "0.001", "0.002"};
    static const char *const kinds[] = {"camera", "bounce"};
    size_t i, k;
    for (i = 0; i < 3; i++) {
        char name[32];
        snprintf(name, sizeof name, "%.*s", (int)strcspn(files[i], "."), files[i]);
        CHECK(tu_run("mkscene %s @/bi-%s --scale %s", name, files[i], scales[i]) == 0,
              "mkscene %s failed", name);
        for (k = 0; k < 2; k++) {
            CHECK(tu_run("raygen @/bi-%s @/bi.rays --kind %s --count 1500", files[i], kinds[k]) == 0,
                  "raygen failed");
            CHECK(tu_run("trace @/bi-%s @/bi.rays @/bi-direct.hits", files[i]) == 0, "trace failed");
            CHECK(tu_run("trace @/bi-%s @/bi.rays @/bi-batched.hits --batched --point-tris 400 "
                         "--proxy-res 32 --memory 40K --scene @/bi-%s.brs", files[i], name) == 0,
                  "trace --batched failed");
            EXPECT(tu_same_file_bytes(tu_scratch("bi-direct.hits"), tu_scratch("bi-batched.hits")),
                   "%s, %s rays: batched and direct hits differ", files[i], kinds[k]);
        }
    }
}

/* examples/tutorials/minimal_batched: its scene file (20 triangles in batching points
** of 2) goes to $TMPDIR and is gone at exit; its batched hits equal the
** direct mode's (it compares them itself and exits 1 otherwise); proxies
** cull rays and batching points are loaded under its memory limit. */
static void test_minimal_batched(void)
{
    const char *old = getenv("TMPDIR");
    char saved[4096], *out;
    unsigned tris = 0, points = 0, tests = 0, culled = 0, queued = 0, loads = 0, bytes = 0;
    int status, rays = 0, hits = 0, misses = 0;
    snprintf(saved, sizeof saved, "%s", old ? old : "");
    CHECK(mkdir(tu_scratch("minimal-tmp"), 0755) == 0, "cannot make the folder for $TMPDIR");
    setenv("TMPDIR", tu_scratch("minimal-tmp"), 1);
    status = tu_run("minimal_batched");
    if (old) setenv("TMPDIR", saved, 1);
    else unsetenv("TMPDIR");
    out = tu_last_stdout();
    CHECK(out, "minimal_batched: no output");
    EXPECT(status == 0 && strstr(out, "batched hits equal the direct mode's, byte for byte"),
           "minimal_batched: exit status %d, printed:\n%s", status, out);
    EXPECT(sscanf(out, "scene: %u triangles in %u batching points", &tris, &points) == 2 &&
           tris == 20 && points == 10, "minimal_batched: %u triangles, %u batching points", tris, points);
    EXPECT(strstr(out, "rays: ") && sscanf(strstr(out, "rays: "), "rays: %d, hits %d, misses %d",
           &rays, &hits, &misses) == 3 && rays == 256 && hits > 0 && misses > 0 && hits + misses == rays,
           "minimal_batched: %d rays, %d hits, %d misses", rays, hits, misses);
    EXPECT(strstr(out, "proxy tests") &&
           sscanf(strstr(out, "proxy tests"), "proxy tests %u, culled %u; queued visits %u; loads %u, %u bytes",
                  &tests, &culled, &queued, &loads, &bytes) == 5 &&
           culled > 0 && culled < tests && queued > 0 && loads > 0 && bytes >= 4096u * loads,
           "minimal_batched: proxy tests %u, culled %u, queued %u, loads %u, %u bytes read",
           tests, culled, queued, loads, bytes);
    EXPECT(tu_dir_entries(tu_scratch("minimal-tmp"), NULL, NULL, NULL, 0) == 0, "minimal_batched left files in $TMPDIR");
    free(out);
    status = tu_run("minimal_batched --bogus");
    out = tu_last_stderr();
    EXPECT(status == 1 && out && strncmp(out, "minimal_batched: ", 17) == 0 && strchr(out, '\n') &&
           strchr(out, '\n')[1] == 0, "minimal_batched --bogus: exit %d, stderr %s", status, out ? out : "");
    free(out);
}

/* README, "Errors": "Programs print that line, exit 1 and leave no output
** file".  A secondary path: the first outputs written, the last one
** (--stats into a folder that does not exist) fails: the hits, the PNG and
** the heat map written before it must go too, and no temporary file stays. */
static void test_late_failure_leaves_nothing(void)
{
    CHECK(tu_run("mkscene crown @/late.ply --scale 0.01") == 0, "mkscene failed");
    CHECK(tu_run("raygen @/late.ply @/late.rays --kind random --count 200") == 0, "raygen failed");
    EXPECT(tu_run("trace @/late.ply @/late.rays @/late.hits --stats @/no-such-dir/s.json") == 1,
           "trace with an unwritable --stats did not exit 1");
    EXPECT(!tu_file_exists(tu_scratch("late.hits")), "trace left its hits after the statistics failed");
    EXPECT(tu_run("render @/late.ply --width 8 --height 6 --spp 1 --out @/late.png --heatmap @/late-heat.png "
                  "--stats @/no-such-dir/s.json") == 1, "render with an unwritable --stats did not exit 1");
    EXPECT(!tu_file_exists(tu_scratch("late.png")) && !tu_file_exists(tu_scratch("late-heat.png")),
           "render left its image or heat map after the statistics failed (png %d, heat map %d)",
           tu_file_exists(tu_scratch("late.png")), tu_file_exists(tu_scratch("late-heat.png")));
    /* --compare writes two heat maps from one buffer of names: both go */
    EXPECT(tu_run("render @/late.ply --compare --memory 50%% --scene @/late.brs --width 8 --height 6 --spp 1 "
                  "--out @/late.png --heatmap @/late-heat.png --stats @/no-such-dir/s.json") == 1,
           "render --compare with an unwritable --stats did not exit 1");
    EXPECT(!tu_file_exists(tu_scratch("late.png")) && !tu_file_exists(tu_scratch("late-heat-noproxy.png")) &&
               !tu_file_exists(tu_scratch("late-heat-proxy.png")),
           "render --compare left an output after the statistics failed (png %d, heat maps %d %d)",
           tu_file_exists(tu_scratch("late.png")), tu_file_exists(tu_scratch("late-heat-noproxy.png")),
           tu_file_exists(tu_scratch("late-heat-proxy.png")));
    EXPECT(!tu_temporary_file_left(), "a temporary file was left");
    EXPECT(tu_run("render @/late.ply --width 8 --height 6 --spp 1 --out @/late.png --heatmap @/late-heat.png "
                  "--stats @/late.json") == 0 && tu_file_exists(tu_scratch("late.png")) &&
           tu_file_exists(tu_scratch("late-heat.png")) && tu_file_exists(tu_scratch("late.json")),
           "a good render did not keep its outputs");
}

/* trace's options of layers 10 and 11 and of proxies in core reach the
** trace (brt_trace_options): in core the proxies are asked only with
** --proxies-in-core, whatever --no-clip and --no-order say, and every
** setting writes the direct mode's bytes. */
static void test_entry_options(void)
{
    static const char *const settings[5] = {"", "--no-clip", "--no-order", "--no-clip --no-order",
                                            "--proxies-in-core"};
    tu_scene m = {0};
    int i;
    CHECK(write_lumpy_mesh(&m, "lumpy.obj"), "cannot write the test mesh");
    tu_scene_free(&m);
    CHECK(tu_run("raygen @/lumpy.obj @/eo.rays --kind bounce --count 2000") == 0, "raygen");
    CHECK(tu_run("trace @/lumpy.obj @/eo.rays @/eo.direct") == 0, "trace --direct");
    for (i = 0; i < 5; i++) {
        double tests;
        CHECK(tu_run("trace @/lumpy.obj @/eo.rays @/eo.hits --batched --point-tris 200 --scene @/eo.brs "
                     "--stats @/eo.json %s", settings[i]) == 0, "trace %s: %s", settings[i], tu_last_stderr());
        EXPECT(tu_same_file_bytes(tu_scratch("eo.hits"), tu_scratch("eo.direct")), "%s: hits differ",
               settings[i]);
        tests = tu_json_file_number(tu_scratch("eo.json"), "proxy_tests");
        EXPECT(i == 4 ? tests > 0 : tests == 0, "trace %s in core: %.0f proxy tests", settings[i], tests);
    }
}

void suite_cli(void)
{
test_run("cli: the source stamp sees mtime (ns and s), size and inode alone", test_source_stamp_parts);
        test_run("cli: --help of every program", test_help);
        test_run("cli: --no-clip, --no-order and --proxies-in-core reach the trace", test_entry_options);
        test_run("cli: a renamed option names its new name (--res, --batch-tris, --batch-instanced)",
                 test_renamed_options);
    test_run("cli: minimal runs", test_minimal);
    test_run("cli: minimal_batched equals the direct mode and removes its scene file",
             test_minimal_batched);
    test_run("cli: raygen is deterministic from --seed", test_raygen_deterministic);
    test_run("cli: raygen camera rays", test_raygen_camera);
    test_run("cli: raygen random rays", test_raygen_random);
    test_run("cli: raygen bounce rays leave a convex surface", test_raygen_bounce);
    test_run("cli: trace equals brute force byte for byte", test_trace_equals_brute_force);
    test_run("cli: trace --stats and --verbose", test_trace_stats);
    test_run("cli: trace --batched writes the bytes of --direct", test_trace_batched);
    test_run("cli: hitdiff table and exit status", test_hitdiff);
    test_run("cli: bad input exits 1 and writes nothing", test_bad_input);
    test_run("cli: PNG decodes with an independent decoder", test_png);
    test_run("cli: PNG write", test_png_write);
    test_run("cli: batched runs need no mesh once the scene file matches", test_batched_needs_no_mesh);
    test_run("cli: --direct says when the mesh exceeds --memory", test_direct_notes_memory);
    test_run("cli: peak_rss_bytes in every program's statistics", test_peak_rss_in_statistics);
    test_run("cli: SIGINT and SIGTERM leave no temporary file", test_interrupts_leave_nothing);
    test_run("cli: a failure after the first outputs leaves none", test_late_failure_leaves_nothing);
    test_run("cli: SIGINT and SIGTERM while tracing leave no output", test_interrupts_while_tracing);
    test_run("cli: Ctrl-C while gzip unpacks a pbrt mesh says interrupted", test_ctrl_c_while_gzip_unpacks);
    test_run("cli: Ctrl-C while a gzip that ignores it unpacks: stopped after the load", test_ctrl_c_while_deaf_gzip_unpacks);
    test_run("cli: hitdiff interrupted while refereeing leaves no --explain file", test_hitdiff_interrupted_explain);
    test_run("cli: trace --batched equals --direct on every built-in scene",
             test_builtin_scenes_batched_equals_direct);
}
