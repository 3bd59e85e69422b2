/*
** examples/bench/bench_bvh.c -- build time, size and single-thread throughput of
** the triangle BVH (bvh.c).  Prints figures, never pass/fail.
**
** Usage: build/bench_bvh [MESH] [--rays N] [--seed S]
**   MESH (OBJ or PLY) defaults to ../shared/data/meshes/bunny_tiny.obj
**   subdivided 4 times (940,544 triangles), or a procedural sphere of ~1M
**   triangles when ../shared is absent.  The rays are build/raygen's
**   (examples/lib/rays.c), deterministic from the seed: camera (a pinhole
**   fitted to the box, pixel order), random (origins in the grown box,
**   uniform directions) and bounce (cosine-weighted from camera hits).
**   Each kind is traced one ray at a time in generation order; times are
**   CPU seconds of this process.  "warm" is the speed of the same rays
**   with their nodes already in cache (see trace_warm()): compute alone.
*/
#include "batchrt.h"
#include "common.h"
#include "rays.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

static const char *prog = "bench_bvh";

/* A UV sphere of 4*rings^2 triangles (vertices shared): a stand-in for a
** scanned mesh when ../shared is absent. */
static void sphere_mesh(brt_mesh *m, uint32_t rings)
{
    const uint32_t seg = 2 * rings;
    uint32_t i, j, t = 0;
    m->vertex_count = (rings + 1) * seg;
    m->triangle_count = 2 * rings * seg;
    m->positions = malloc(3 * (size_t)m->vertex_count * sizeof(float));
    m->indices = malloc(3 * (size_t)m->triangle_count * sizeof(uint32_t));
    if (!m->positions || !m->indices) ex_die(prog, "out of memory");
    for (i = 0; i <= rings; i++)
        for (j = 0; j < seg; j++) {
            const double pi = 3.14159265358979323846;
            const double th = pi * i / rings, ph = 2 * pi * j / seg;
            float *p = m->positions + 3 * (size_t)(i * seg + j);
            p[0] = (float)(sin(th) * cos(ph));
            p[1] = (float)cos(th);
            p[2] = (float)(sin(th) * sin(ph));
        }
    for (i = 0; i < rings; i++)
        for (j = 0; j < seg; j++) {
            const uint32_t a = i * seg + j, b = i * seg + (j + 1) % seg;
            uint32_t *q = m->indices + 6 * (size_t)t++;
            q[0] = a; q[1] = a + seg; q[2] = b;
            q[3] = b; q[4] = a + seg; q[5] = b + seg;
        }
}

/* Splits every triangle into four at its edge midpoints (flat), with
** three vertices of its own per triangle; midpoints of a shared edge are
** the same floats from both sides, since a+b == b+a. */
static void subdivide(brt_mesh *m)
{
    brt_mesh out;
    uint32_t t;
    int j, k, a;
    out.triangle_count = 4 * m->triangle_count;
    out.vertex_count = 3 * out.triangle_count;
    out.positions = malloc(3 * (size_t)out.vertex_count * sizeof(float));
    out.indices = malloc(3 * (size_t)out.triangle_count * sizeof(uint32_t));
    if (!out.positions || !out.indices) ex_die(prog, "out of memory");
    for (t = 0; t < 3 * out.triangle_count; t++) out.indices[t] = t;
    for (t = 0; t < m->triangle_count; t++) {
        float p[6][3];   /* corners 0-2, midpoints of 01, 12, 20 */
        static const int sub[4][3] = {{0, 3, 5}, {3, 1, 4}, {5, 4, 2}, {3, 4, 5}};
        for (j = 0; j < 3; j++)
            memcpy(p[j], m->positions + 3 * (size_t)m->indices[3 * (size_t)t + j], sizeof p[j]);
        for (j = 0; j < 3; j++)
            for (a = 0; a < 3; a++) p[3 + j][a] = 0.5f * (p[j][a] + p[(j + 1) % 3][a]);
        for (k = 0; k < 4; k++)
            for (j = 0; j < 3; j++)
                memcpy(out.positions + 9 * (4 * (size_t)t + k) + 3 * j, p[sub[k][j]], sizeof p[0]);
    }
    brt_mesh_free(m);
    *m = out;
}

/* The default is the shared bunny_tiny subdivided 4 times (940,544
** triangles, the mesh of the Embree figures the goal refers to). */
static void load_mesh(const char *path, brt_mesh *m)
{
    static const char *shared = "../shared/data/meshes/bunny_tiny.obj";
    brt_error err;
    struct stat st;
    int subdivisions = 0, i;
    if (!path && stat(shared, &st) == 0) {
        path = shared;
        subdivisions = 4;
    }
    if (!path) {
        printf("mesh: procedural sphere\n");
        sphere_mesh(m, 512);
        return;
    }
    printf("mesh: %s%s\n", path, subdivisions ? ", subdivided 4 times" : "");
    if (brt_mesh_load(path, m, &err) != BRT_OK) ex_die(prog, "%s", err.message);
    for (i = 0; i < subdivisions; i++) subdivide(m);
}

/* CPU seconds of this process: on a busy machine, wall time would
** measure the other processes too. */
/* Traces rays [begin, end) one at a time; returns how many hit. */
static size_t trace_range(const brt_bvh *bvh, const brt_ray *rays, brt_hit *hits,
                          size_t begin, size_t end)
{
    size_t i, hit_count = 0;
    for (i = begin; i < end; i++) {
        brt_hit_clear(&hits[i]);
        brt_bvh_intersect(bvh, &rays[i], &hits[i]);
        hit_count += hits[i].prim != BRT_NO_PRIM;
    }
    return hit_count;
}

/* The warm time: each block of 256 rays is traced once untimed, which
** brings its nodes and triangles into cache (a few hundred KB), then
** again, timed.  So it is the cost of the rays without waiting on
** memory; its gap to the cold time is what DRAM latency costs. */
static double trace_warm(const brt_bvh *bvh, const brt_ray *rays, brt_hit *hits, size_t n)
{
    double seconds = 0.0;
    size_t b;
    for (b = 0; b < n; b += 256) {
        const size_t end = n - b < 256 ? n : b + 256;
        double t0;
        trace_range(bvh, rays, hits, b, end);
        t0 = ex_cpu_seconds();
        trace_range(bvh, rays, hits, b, end);
        seconds += ex_cpu_seconds() - t0;
    }
    return seconds;
}

static void measure(const char *kind, const brt_bvh *bvh, const brt_ray *rays,
                    brt_hit *hits, size_t n)
{
    const double t0 = ex_cpu_seconds();
    const size_t hit_count = trace_range(bvh, rays, hits, 0, n);
    const double cold = ex_cpu_seconds() - t0, warm = trace_warm(bvh, rays, hits, n);
    printf("| %s | %zu | %.3f | %.2f | %.2f | %.1f %% |\n", kind, n, cold, (double)n / cold * 1e-6,
           (double)n / warm * 1e-6, 100.0 * (double)hit_count / (double)n);
}

int main(int argc, char **argv)
{
    const char *path = NULL;
    size_t n = 1u << 20;
    uint64_t seed = 1;
    brt_mesh mesh;
    brt_bvh *bvh;
    brt_ray *rays;
    brt_hit *hits;
    ex_camera cam;
    float lo[3], hi[3];
    double t0, seconds;
    uint32_t side;
    int i;
    for (i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--help") || !strcmp(argv[i], "-h")) {
            printf("usage: %s [MESH] [--rays N] [--seed S]\n"
                   "Builds a BVH over MESH (default: the shared bunny_tiny subdivided 4\n"
                   "times, or a procedural sphere) and traces N camera, random and bounce\n"
                   "rays (default 1048576 each) on one thread.\n", prog);
            return 0;
        } else if (!strcmp(argv[i], "--rays")) {
            n = (size_t)ex_parse_u64(prog, "--rays", ex_option_value(prog, argc, argv, &i), 1, 1u << 28);
        } else if (!strcmp(argv[i], "--seed")) {
            seed = ex_parse_u64(prog, "--seed", ex_option_value(prog, argc, argv, &i), 0, UINT64_MAX);
        } else if (argv[i][0] == '-') {
            ex_unknown_option(prog, argv[i]);
        } else {
            path = argv[i];
        }
    }
    load_mesh(path, &mesh);
    if (mesh.triangle_count == 0) ex_die(prog, "the mesh has no triangles");
    brt_mesh_bounds(&mesh, lo, hi);
    t0 = ex_cpu_seconds();
    if (brt_bvh_build(mesh.positions, mesh.indices, mesh.triangle_count, NULL, &bvh) != BRT_OK)
        ex_die(prog, "BVH build failed");
    seconds = ex_cpu_seconds() - t0;
    printf("triangles %u  build %.3f s (%.3f s per million)  %.1f bytes/triangle\n",
           (unsigned)mesh.triangle_count, seconds, seconds * 1e6 / mesh.triangle_count,
           (double)brt_bvh_memory_bytes(bvh) / mesh.triangle_count);

    rays = malloc(n * sizeof *rays);
    hits = malloc(n * sizeof *hits);
    if (!rays || !hits) ex_die(prog, "out of memory");
    side = (uint32_t)ceil(sqrt((double)n));
    ex_camera_fit(&cam, lo, hi, side, (uint32_t)((n + side - 1) / side));
    ex_rays_camera(&cam, rays, n, &seed);
    printf("\n| rays | count | cold CPU s | cold Mrays/s | warm Mrays/s | hit |\n"
           "|---|---:|---:|---:|---:|---:|\n");
    measure("camera", bvh, rays, hits, n);
    ex_rays_random(lo, hi, rays, n, &seed);
    measure("random", bvh, rays, hits, n);
    if (!ex_rays_bounce(&mesh, bvh, &cam, rays, n, &seed)) ex_die(prog, "the camera sees no triangle");
    measure("bounce", bvh, rays, hits, n);
    free(rays); free(hits);
    brt_bvh_free(bvh);
    brt_mesh_free(&mesh);
    return 0;
}
