/*
** examples/bench_bvh.c -- build time, size and single-thread throughput of
** the triangle BVH (bvh.c).  Prints figures, never pass/fail.
**
** Usage: build/bench_bvh [MESH] [--rays N] [--seed S]
**   MESH (OBJ or PLY) defaults to ../shared/data/meshes/bunny_tiny.obj
**   subdivided 4 times (940,544 triangles), or a procedural sphere of ~1M
**   triangles when ../shared is absent.  Rays are generated here, deterministically
**   from the seed: camera (a pinhole looking at the mesh), random (origin
**   in the box, uniform direction) and bounce (from the camera's hit
**   points, or random surface points where the camera missed, in a
**   uniform direction, tnear = 1e-5 of the box size).
*/
#include "batchrt.h"
#include "common.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
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

/* A uniform direction (rejection sampling in the unit ball). */
static void random_dir(uint64_t *st, float d[3])
{
    float len;
    do {
        d[0] = 2 * brt_random_float(st) - 1;
        d[1] = 2 * brt_random_float(st) - 1;
        d[2] = 2 * brt_random_float(st) - 1;
        len = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    } while (len > 1.0f || len < 1e-4f);
}

typedef struct frame {
    float lo[3], hi[3], c[3], radius;   /* box, centre, half diagonal */
    float dist;                         /* of the camera from c */
} frame;

static void set_ray(brt_ray *r, const float org[3], const float dir[3], float tnear)
{
    memcpy(r->org, org, sizeof r->org);
    memcpy(r->dir, dir, sizeof r->dir);
    r->tnear = tnear;
    r->tfar = INFINITY;
}

/* As build/raygen: a 45 degree pinhole from +z and a little above, just
** far enough back for the whole box to be in view (f->dist). */
static const float back[3] = {0.0f, 0.330f, 0.944f}, right[3] = {1, 0, 0};
static const float up[3] = {0.0f, 0.944f, -0.330f};
#define TAN_HALF_FOV 0.41421f

static float camera_distance(const frame *f)
{
    float dist = 0;
    int corner, a;
    for (corner = 0; corner < 8; corner++) {
        float o[3], ob = 0, orr = 0, ou = 0, d;
        for (a = 0; a < 3; a++) {
            o[a] = ((corner >> a) & 1 ? f->hi[a] : f->lo[a]) - f->c[a];
            ob += o[a] * back[a];
            orr += o[a] * right[a];
            ou += o[a] * up[a];
        }
        d = ob + (fabsf(orr) > fabsf(ou) ? fabsf(orr) : fabsf(ou)) / TAN_HALF_FOV;
        if (d > dist) dist = d;
    }
    return 1.05f * dist;
}

static void camera_ray(const frame *f, float sx, float sy, brt_ray *r)
{
    float eye[3], dir[3];
    int a;
    for (a = 0; a < 3; a++) {
        eye[a] = f->c[a] + f->dist * back[a];
        dir[a] = -back[a] + TAN_HALF_FOV * ((2 * sx - 1) * right[a] + (1 - 2 * sy) * up[a]);
    }
    set_ray(r, eye, dir, 0.0f);
}

static void camera_rays(const frame *f, brt_ray *rays, size_t n)
{
    const size_t side = (size_t)ceil(sqrt((double)n));
    size_t i;
    for (i = 0; i < n; i++)
        camera_ray(f, ((float)(i % side) + 0.5f) / (float)side,
                   ((float)(i / side) + 0.5f) / (float)side, &rays[i]);
}

/* Origins in the box grown by 5 % of its longest side, uniform directions. */
static void random_rays(const frame *f, uint64_t *st, brt_ray *rays, size_t n)
{
    float grow = 0, org[3], dir[3];
    size_t i;
    int a;
    for (a = 0; a < 3; a++)
        if (0.05f * (f->hi[a] - f->lo[a]) > grow) grow = 0.05f * (f->hi[a] - f->lo[a]);
    for (i = 0; i < n; i++) {
        for (a = 0; a < 3; a++)
            org[a] = f->lo[a] - grow + (f->hi[a] - f->lo[a] + 2 * grow) * brt_random_float(st);
        random_dir(st, dir);
        set_ray(&rays[i], org, dir, 0.0f);
    }
}

/* A cosine-weighted direction about the normal n (Malley's method, with
** the tangent frame of Duff et al. 2017), as build/raygen draws them. */
static void cosine_dir(uint64_t *st, const float n_in[3], float dir[3])
{
    const float r = sqrtf(brt_random_float(st)), phi = 6.2831853f * brt_random_float(st);
    const float x = r * cosf(phi), y = r * sinf(phi), z = sqrtf(1.0f - r * r > 0 ? 1.0f - r * r : 0);
    float n[3], t[3], b[3], len, sg, a_, c;
    int k;
    len = sqrtf(n_in[0] * n_in[0] + n_in[1] * n_in[1] + n_in[2] * n_in[2]);
    for (k = 0; k < 3; k++) n[k] = len > 0 ? n_in[k] / len : (k == 2);
    sg = n[2] >= 0 ? 1.0f : -1.0f;
    a_ = -1.0f / (sg + n[2]);
    c = n[0] * n[1] * a_;
    t[0] = 1.0f + sg * n[0] * n[0] * a_; t[1] = sg * c; t[2] = -sg * n[0];
    b[0] = c; b[1] = sg + n[1] * n[1] * a_; b[2] = -n[1];
    for (k = 0; k < 3; k++) dir[k] = x * t[k] + y * b[k] + z * n[k];
}

/* From each camera ray's hit (a random image point's where it missed),
** in a cosine-weighted direction of the hemisphere facing the camera,
** tnear a hair above 0.  Coherent origins, incoherent directions. */
static void bounce_rays(const brt_mesh *m, const frame *f, const brt_bvh *bvh,
                        const brt_ray *cam, uint64_t *st, brt_ray *rays, size_t n)
{
    size_t i;
    int a, attempt;
    for (i = 0; i < n; i++) {
        brt_ray in = cam[i];
        brt_hit h;
        const float *p[3];
        float e1[3], e2[3], nrm[3], org[3], dir[3], facing = 0;
        brt_hit_clear(&h);
        brt_bvh_intersect(bvh, &in, &h);
        for (attempt = 0; h.prim == BRT_NO_PRIM && attempt < 1000; attempt++) {
            camera_ray(f, brt_random_float(st), brt_random_float(st), &in);
            brt_bvh_intersect(bvh, &in, &h);
        }
        if (h.prim == BRT_NO_PRIM) { rays[i] = in; continue; }
        for (a = 0; a < 3; a++) p[a] = m->positions + 3 * (size_t)m->indices[3 * (size_t)h.prim + a];
        for (a = 0; a < 3; a++) {
            e1[a] = p[1][a] - p[0][a];
            e2[a] = p[2][a] - p[0][a];
        }
        for (a = 0; a < 3; a++) {
            nrm[a] = e1[(a + 1) % 3] * e2[(a + 2) % 3] - e1[(a + 2) % 3] * e2[(a + 1) % 3];
            facing += nrm[a] * in.dir[a];
        }
        if (facing > 0) for (a = 0; a < 3; a++) nrm[a] = -nrm[a];
        cosine_dir(st, nrm, dir);
        for (a = 0; a < 3; a++) org[a] = in.org[a] + h.t * in.dir[a];
        set_ray(&rays[i], org, dir, 1e-5f * f->radius);
    }
}

/* CPU seconds of this process: on a busy machine, wall time would
** measure the other processes too. */
static double cpu_seconds(void)
{
    return (double)clock() / CLOCKS_PER_SEC;
}

static double trace(const brt_bvh *bvh, const brt_ray *rays, brt_hit *hits,
                    size_t n, size_t *hit_count)
{
    const double t0 = cpu_seconds();
    size_t i;
    *hit_count = 0;
    for (i = 0; i < n; i++) {
        brt_hit_clear(&hits[i]);
        brt_bvh_intersect(bvh, &rays[i], &hits[i]);
        *hit_count += hits[i].prim != BRT_NO_PRIM;
    }
    return cpu_seconds() - t0;
}

static void report(const char *kind, double seconds, size_t n, size_t hit_count)
{
    printf("%-7s %8zu rays  %6.3f s  %6.2f Mrays/s  (%.1f%% hit)\n", kind, n, seconds,
           (double)n / seconds * 1e-6, 100.0 * (double)hit_count / (double)n);
}

int main(int argc, char **argv)
{
    const char *path = NULL;
    size_t n = 1u << 20, hit_count;
    uint64_t seed = 1;
    brt_mesh mesh;
    brt_bvh *bvh;
    brt_ray *rays, *cam;
    brt_hit *hits;
    frame f;
    double t0, seconds;
    int i, a;
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
            ex_die(prog, "unknown option %s (see --help)", argv[i]);
        } else {
            path = argv[i];
        }
    }
    load_mesh(path, &mesh);
    if (mesh.triangle_count == 0) ex_die(prog, "the mesh has no triangles");
    brt_mesh_bounds(&mesh, f.lo, f.hi);
    f.radius = 0;
    for (a = 0; a < 3; a++) {
        f.c[a] = 0.5f * (f.lo[a] + f.hi[a]);
        f.radius += 0.25f * (f.hi[a] - f.lo[a]) * (f.hi[a] - f.lo[a]);
    }
    f.radius = sqrtf(f.radius);
    f.dist = camera_distance(&f);
    t0 = cpu_seconds();
    if (brt_bvh_build(mesh.positions, mesh.indices, mesh.triangle_count, NULL, &bvh) != BRT_OK)
        ex_die(prog, "BVH build failed");
    seconds = cpu_seconds() - t0;
    printf("triangles %u  build %.3f s (%.3f s per million)  %.1f bytes/triangle\n",
           (unsigned)mesh.triangle_count, seconds, seconds * 1e6 / mesh.triangle_count,
           (double)brt_bvh_memory_bytes(bvh) / mesh.triangle_count);

    rays = malloc(n * sizeof *rays);
    cam = malloc(n * sizeof *cam);
    hits = malloc(n * sizeof *hits);
    if (!rays || !cam || !hits) ex_die(prog, "out of memory");
    camera_rays(&f, cam, n);
    seconds = trace(bvh, cam, hits, n, &hit_count);
    report("camera", seconds, n, hit_count);
    random_rays(&f, &seed, rays, n);
    seconds = trace(bvh, rays, hits, n, &hit_count);
    report("random", seconds, n, hit_count);
    bounce_rays(&mesh, &f, bvh, cam, &seed, rays, n);
    seconds = trace(bvh, rays, hits, n, &hit_count);
    report("bounce", seconds, n, hit_count);
    free(rays); free(cam); free(hits);
    brt_bvh_free(bvh);
    brt_mesh_free(&mesh);
    return 0;
}
