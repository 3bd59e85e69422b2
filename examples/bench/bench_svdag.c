/*
** examples/bench/bench_svdag.c -- what the conservative voxel proxies (svdag.c,
** after Molenaar and Eisemann 2020) cost and how fast they answer.
** Prints figures, never pass/fail.
**
** Usage: build/bench_svdag [MESH...] [--rays N] [--proxy-res R] [--seed S] [--no-table]
**        build/bench_svdag --scene landscape|island|crown [--scale S] [--point-tris N]
**                          [--rays N] [--proxy-res R] [--seed S]
**   MESH defaults to bunny_tiny, bunny and dragon from ../shared/data/meshes
**   (the .gz ones unpacked with gzip into /tmp), whichever are present.
** For each mesh:
**   - throughput on the same rays (half camera rays, half rays from a
**     sphere around the mesh aimed into its box): the proxy ray cast at
**     --proxy-res beside the BVH's closest hit, single thread, in CPU time (the
**     process's own, so that other jobs on a shared machine do not count),
**     and how many BVH hits the proxy missed (must be 0) or added (false hits);
**   - voxelization and DAG build time, and DAG bytes, at res 16..512
**     (the paper's Fig. 2, left), as a Markdown table.
** With --scene: the proxy tests of a render of a built-in scene, culled
** casts and hits apart, for instruction counts with callgrind (see
** "Scene mode" below and the README's "The proxy cast").
*/
#include "common.h"
#include "rays.h"
#include "scenes.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

static const char *const prog = "bench_svdag";

typedef struct options {
    const char *meshes[16];
    int mesh_count;
    uint64_t rays, seed;
    uint32_t res, point_tris;
    const char *scene;      /* --scene: the render's proxy tests instead */
    double scale;
    int no_table;
} options;

static void usage(void)
{
    printf("usage: build/bench_svdag [MESH...] [options]\n"
           "Benchmarks the voxel proxies: ray cast Mrays/s beside the BVH's closest hit\n"
           "on the same rays, voxelization and DAG build time, DAG bytes at res 16..512.\n"
           "Without MESH: bunny_tiny, bunny, dragon from ../shared/data/meshes.\n"
           "\n"
           "  --rays N    rays per throughput run (default 1000000)\n"
           "  --proxy-res R  proxy resolution of the throughput run (default 128)\n"
           "  --seed S    ray generator seed (default 1)\n"
           "  --no-table  throughput only, no build/memory table\n"
           "  --scene NAME  instead: the proxy tests of a render of a built-in scene\n"
           "              (batching points, proxies, camera and bounce rays as render's),\n"
           "              culled casts and hits apart (for callgrind, see the source)\n"
           "  --scale S   scene scale (default 2: the crown 200 000 triangles)\n"
           "  --point-tris N  triangles per batching point (default 10000)\n"
           "  --help      this text\n");
}

static void parse_options(int argc, char **argv, options *o)
{
    int i;
    memset(o, 0, sizeof *o);
    o->rays = 1000000;
    o->res = 128;
    o->seed = 1;
    o->point_tris = 10000;
    o->scale = 2;
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (strcmp(a, "--rays") == 0)
            o->rays = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 1, 100000000);
        else if (strcmp(a, "--seed") == 0)
            o->seed = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 0, UINT64_MAX);
        else if (strcmp(a, "--no-table") == 0) o->no_table = 1;
        else if (strcmp(a, "--scene") == 0) {
            o->scene = ex_option_value(prog, argc, argv, &i);
            if (!ex_scene_is_builtin(o->scene)) ex_die(prog, "--scene: '%s' is not a built-in scene", o->scene);
        } else if (strcmp(a, "--scale") == 0)
            o->scale = ex_parse_double(prog, a, ex_option_value(prog, argc, argv, &i), 0.01, 100);
        else if (strcmp(a, "--point-tris") == 0)
            o->point_tris = (uint32_t)ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 1, 100000000);
        else if (strcmp(a, "--proxy-res") == 0)
            o->res = ex_parse_resolution(prog, a, ex_option_value(prog, argc, argv, &i));
        else if (a[0] == '-' && a[1] != 0) ex_unknown_option(prog, a);
        else if (o->mesh_count < 16) o->meshes[o->mesh_count++] = a;
        else ex_die(prog, "too many meshes (at most 16)");
    }
}

/* The shared mesh NAME as a plain file path, or NULL when absent. */
static const char *shared_mesh(const char *name, char *buf, size_t size)
{
    char src[512], cmd[2200];
    struct stat st;
    size_t len = strlen(name);
    snprintf(src, sizeof src, "../shared/data/meshes/%s", name);
    if (stat(src, &st) != 0) return NULL;
    if (len < 3 || strcmp(name + len - 3, ".gz") != 0) {
        snprintf(buf, size, "%s", src);
        return buf;
    }
    snprintf(buf, size, "/tmp/batchrt_bench_%.*s", (int)(len - 3), name);
    if (stat(buf, &st) == 0) return buf;
    snprintf(cmd, sizeof cmd, "gzip -dc '%s' > '%s.part' && mv '%s.part' '%s'", src, buf, buf, buf);
    return system(cmd) == 0 ? buf : NULL;
}

/* ===================================================================== */
/* Rays                                                                  */
/* ===================================================================== */

static void unit_vector(uint64_t *rng, float v[3])
{
    float len;
    do {
        int i;
        for (i = 0; i < 3; i++) v[i] = 2 * brt_random_float(rng) - 1;
        len = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    } while (len > 1 || len < 1e-6f);
    len = sqrtf(len);
    v[0] /= len; v[1] /= len; v[2] /= len;
}

/* Half camera rays (a pinhole at a fixed corner looking at the centre),
** half rays from a sphere around the box aimed at random points in it. */
static brt_ray *make_rays(const brt_mesh *mesh, uint64_t count, uint64_t seed)
{
    brt_ray *rays = malloc(count * sizeof *rays);
    float bmin[3], bmax[3], centre[3], radius = 0;
    uint64_t n, rng = seed;
    int i;
    if (!rays) ex_die(prog, "out of memory for %llu rays", (unsigned long long)count);
    brt_mesh_bounds(mesh, bmin, bmax);
    for (i = 0; i < 3; i++) {
        centre[i] = 0.5f * (bmin[i] + bmax[i]);
        radius += (bmax[i] - bmin[i]) * (bmax[i] - bmin[i]);
    }
    radius = 0.5f * sqrtf(radius);
    for (n = 0; n < count; n++) {
        brt_ray *r = &rays[n];
        float from[3];
        if (n % 2 == 0) {
            uint64_t side = 1024, pixel = (n / 2) % (side * side);
            float px = ((float)(pixel % side) + 0.5f) / side - 0.5f;
            float py = ((float)(pixel / side) + 0.5f) / side - 0.5f;
            for (i = 0; i < 3; i++) r->org[i] = centre[i] + 2.2f * radius * (i == 2 ? 1.0f : 0.5f);
            for (i = 0; i < 3; i++) r->dir[i] = centre[i] - r->org[i];
            r->dir[0] += px * radius * 2.2f;
            r->dir[1] += py * radius * 2.2f;
        } else {
            unit_vector(&rng, from);
            for (i = 0; i < 3; i++) {
                float target = bmin[i] + (bmax[i] - bmin[i]) * brt_random_float(&rng);
                r->org[i] = centre[i] + 2 * radius * from[i];
                r->dir[i] = target - r->org[i];
            }
        }
        r->tnear = 0;
        r->tfar = INFINITY;
    }
    return rays;
}

/* ===================================================================== */
/* Measurements                                                          */
/* ===================================================================== */

/* Seconds of CPU time used by this process. */
typedef struct build_figures {
    double voxelize_seconds, dag_seconds;
    uint64_t voxels;
    uint32_t dag_nodes;
    size_t dag_bytes;
} build_figures;

static void build_proxy(const brt_mesh *mesh, uint32_t res, brt_svdag **dag,
                        brt_proxy *proxy, build_figures *f)
{
    brt_grid grid;
    float bmin[3], bmax[3];
    double start = brt_seconds();
    brt_mesh_bounds(mesh, bmin, bmax);
    ex_check(prog, brt_grid_init(&grid, bmin, bmax, res), NULL);
    ex_check(prog, brt_voxelize(&grid, mesh->positions, mesh->indices, mesh->triangle_count), NULL);
    f->voxelize_seconds = brt_seconds() - start;
    f->voxels = brt_grid_count(&grid);
    start = brt_seconds();
    ex_check(prog, brt_svdag_create(dag), NULL);
    ex_check(prog, brt_svdag_add(*dag, &grid, proxy), NULL);
    f->dag_seconds = brt_seconds() - start;
    f->dag_nodes = brt_svdag_node_count(*dag);
    f->dag_bytes = brt_svdag_memory_bytes(*dag);
    brt_grid_free(&grid);
}

static void throughput(const brt_mesh *mesh, const options *o)
{
    brt_ray *rays = make_rays(mesh, o->rays, o->seed);
    brt_hit *hits = malloc(o->rays * sizeof *hits);
    brt_bvh *bvh;
    brt_svdag *dag;
    brt_proxy proxy;
    build_figures f;
    uint64_t n, bvh_hits = 0, proxy_hits = 0, missed = 0;
    double start, bvh_seconds, proxy_seconds;
    if (!hits) ex_die(prog, "out of memory for hits");
    ex_check(prog, brt_bvh_build(mesh->positions, mesh->indices, mesh->triangle_count, NULL, &bvh), NULL);
    build_proxy(mesh, o->res, &dag, &proxy, &f);
    start = ex_cpu_seconds();
    for (n = 0; n < o->rays; n++) {
        brt_hit_clear(&hits[n]);
        brt_bvh_intersect(bvh, &rays[n], &hits[n]);
    }
    bvh_seconds = ex_cpu_seconds() - start;
    start = ex_cpu_seconds();
    for (n = 0; n < o->rays; n++) {
        float t;
        int got = brt_proxy_raycast(dag, &proxy, &rays[n], 0, INFINITY, &t);
        proxy_hits += got;
        /* Stored in the ray's tnear slot so the check below is outside the timing. */
        rays[n].tnear = got ? t : -INFINITY;
    }
    proxy_seconds = ex_cpu_seconds() - start;
    for (n = 0; n < o->rays; n++)
        if (hits[n].prim != BRT_NO_PRIM) {
            bvh_hits++;
            missed += !(rays[n].tnear != -INFINITY && rays[n].tnear <= hits[n].t);
        }
    printf("rays %llu (half camera, half from a sphere into the box), res %u\n",
           (unsigned long long)o->rays, o->res);
    printf("  BVH closest hit   %8.2f Mrays/s   %llu hits\n", o->rays / bvh_seconds * 1e-6,
           (unsigned long long)bvh_hits);
    printf("  proxy ray cast    %8.2f Mrays/s   %llu hits (%.1f%% more than the BVH), "
           "%llu BVH hits missed or entered late\n",
           o->rays / proxy_seconds * 1e-6, (unsigned long long)proxy_hits,
           bvh_hits ? 100.0 * ((double)proxy_hits - bvh_hits) / bvh_hits : 0.0,
           (unsigned long long)missed);
    printf("  speed-up of the proxy over the BVH: %.2fx\n", bvh_seconds / proxy_seconds);
    brt_svdag_free(dag);
    brt_bvh_free(bvh);
    free(hits);
    free(rays);
}

static void memory_table(const brt_mesh *mesh)
{
    double mesh_bytes = 12.0 * mesh->vertex_count + 12.0 * mesh->triangle_count;
    uint32_t res;
    printf("\n| res | voxels | DAG nodes | DAG bytes | %% of mesh bytes | voxelize s | DAG s |\n"
           "|---:|---:|---:|---:|---:|---:|---:|\n");
    for (res = 16; res <= 512; res *= 2) {
        brt_svdag *dag;
        brt_proxy proxy;
        build_figures f;
        build_proxy(mesh, res, &dag, &proxy, &f);
        printf("| %u | %llu | %u | %lu | %.3f | %.3f | %.3f |\n", res,
               (unsigned long long)f.voxels, f.dag_nodes, (unsigned long)f.dag_bytes,
               100.0 * f.dag_bytes / mesh_bytes, f.voxelize_seconds, f.dag_seconds);
        brt_svdag_free(dag);
    }
}

/* ===================================================================== */
/* Scene mode: the proxy tests of a render                               */
/* ===================================================================== */

/*
** --scene NAME: the built-in scene cut into batching points as
** brt_scene_build cuts it (halves of the centroids along the longest axis,
** at a multiple of --point-tris near the middle), one 128^3 proxy each in
** one shared DAG, and the render's rays: half camera rays from the scene's
** default view, half Lambert bounces from their hits.  Each ray is tested,
** as the render's scheduler tests it, against every batching point whose
** box it enters before its closest hit, on [tnear, closest hit], with no
** entry wanted.  The tests are then cast again split by answer, each kind
** in its own function (cast_culled returns the misses, cast_hits the hits)
** so that
**     valgrind --tool=callgrind --toggle-collect=cast_culled build/bench_svdag ...
** counts the instructions of the culled casts alone (divide by "culled").
*/
typedef struct cast_task {
    brt_ray ray;            /* tnear / tfar: the tested segment */
    uint32_t point;
} cast_task;

typedef struct point_set {
    brt_svdag *dag;
    brt_proxy *proxies;
    float (*box)[6];
    uint32_t count;
} point_set;

static const float *sort_centroids;
static int sort_axis;

static int by_centroid(const void *a, const void *b)
{
    float x = sort_centroids[3 * *(const uint32_t *)a + sort_axis];
    float y = sort_centroids[3 * *(const uint32_t *)b + sort_axis];
    return (x > y) - (x < y);
}

/* One batching point: its triangles' proxy added to the shared DAG. */
static void add_batch(const brt_mesh *mesh, const uint32_t *tris, uint32_t count,
                      uint32_t res, point_set *b)
{
    uint32_t *idx = malloc(3 * (size_t)count * sizeof *idx), t;
    float *bmin = b->box[b->count], *bmax = bmin + 3;
    brt_grid grid;
    int i;
    if (!idx) ex_die(prog, "out of memory for a batching point");
    for (t = 0; t < 3 * count; t++) idx[t] = mesh->indices[3 * (size_t)tris[t / 3] + t % 3];
    for (i = 0; i < 3; i++) { bmin[i] = INFINITY; bmax[i] = -INFINITY; }
    for (t = 0; t < 3 * count; t++)
        for (i = 0; i < 3; i++) {
            float v = mesh->positions[3 * (size_t)idx[t] + i];
            bmin[i] = fminf(bmin[i], v);
            bmax[i] = fmaxf(bmax[i], v);
        }
    ex_check(prog, brt_grid_init(&grid, bmin, bmax, res), NULL);
    ex_check(prog, brt_voxelize(&grid, mesh->positions, idx, count), NULL);
    ex_check(prog, brt_svdag_add(b->dag, &grid, &b->proxies[b->count]), NULL);
    b->count++;
    brt_grid_free(&grid);
    free(idx);
}

/* Splits tris[0..count) as brt_scene_build does, adding the parts. */
static void split_points(const brt_mesh *mesh, const float *centroids, uint32_t *tris,
                          uint32_t count, uint32_t point_tris, uint32_t res, point_set *b)
{
    float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    uint32_t t, parts, k;
    int i;
    if (count <= point_tris) {
        add_batch(mesh, tris, count, res, b);
        return;
    }
    for (t = 0; t < count; t++)
        for (i = 0; i < 3; i++) {
            lo[i] = fminf(lo[i], centroids[3 * (size_t)tris[t] + i]);
            hi[i] = fmaxf(hi[i], centroids[3 * (size_t)tris[t] + i]);
        }
    sort_axis = 0;
    for (i = 1; i < 3; i++)
        if (hi[i] - lo[i] > hi[sort_axis] - lo[sort_axis]) sort_axis = i;
    sort_centroids = centroids;
    qsort(tris, count, sizeof *tris, by_centroid);
    parts = (count + point_tris - 1) / point_tris;
    k = parts / 2 * point_tris;
    split_points(mesh, centroids, tris, k, point_tris, res, b);
    split_points(mesh, centroids, tris + k, count - k, point_tris, res, b);
}

static void build_points(const brt_mesh *mesh, uint32_t point_tris, uint32_t res, point_set *b)
{
    uint32_t n = mesh->triangle_count, t, parts = (n + point_tris - 1) / point_tris;
    uint32_t *tris = malloc((size_t)n * sizeof *tris);
    float *centroids = malloc(3 * (size_t)n * sizeof *centroids);
    int i, k;
    b->proxies = malloc(2 * (size_t)parts * sizeof *b->proxies);
    b->box = malloc(2 * (size_t)parts * sizeof *b->box);
    if (!tris || !centroids || !b->proxies || !b->box) ex_die(prog, "out of memory for batching points");
    for (t = 0; t < n; t++) {
        tris[t] = t;
        for (i = 0; i < 3; i++) {
            float s = 0;
            for (k = 0; k < 3; k++) s += mesh->positions[3 * (size_t)mesh->indices[3 * (size_t)t + k] + i];
            centroids[3 * (size_t)t + i] = s / 3;
        }
    }
    b->count = 0;
    ex_check(prog, brt_svdag_create(&b->dag), NULL);
    split_points(mesh, centroids, tris, n, point_tris, res, b);
    free(tris);
    free(centroids);
}

/* Entry of a ray into a box before tfar, or 0. */
static int box_entered(const brt_ray *ray, const float box[6], float tfar)
{
    float lo = ray->tnear, hi = tfar;
    int i;
    for (i = 0; i < 3; i++) {
        float inv = 1.0f / ray->dir[i];
        float a = (box[i] - ray->org[i]) * inv, c = (box[3 + i] - ray->org[i]) * inv;
        lo = fmaxf(lo, fminf(a, c));
        hi = fminf(hi, fmaxf(a, c));
    }
    return lo <= hi;
}

/* The render's proxy tests of the rays: a task per box entered before
** the closest hit, in *tasks (malloc'd); their number. */
static size_t make_tasks(const brt_mesh *mesh, const point_set *b, const brt_ray *rays,
                         size_t count, cast_task **tasks)
{
    brt_bvh *bvh;
    size_t n = 0, cap = 4 * count + 16, i;
    uint32_t k;
    cast_task *out = malloc(cap * sizeof *out);
    ex_check(prog, brt_bvh_build(mesh->positions, mesh->indices, mesh->triangle_count, NULL, &bvh), NULL);
    for (i = 0; i < count && out; i++) {
        brt_hit hit;
        brt_hit_clear(&hit);
        brt_bvh_intersect(bvh, &rays[i], &hit);
        for (k = 0; k < b->count && out; k++) {
            if (!box_entered(&rays[i], b->box[k], hit.t)) continue;
            if (n == cap) out = brt_grow(out, &cap, n + 1, sizeof *out);   /* NULL: dies below */
            if (!out) break;
            out[n].ray = rays[i];
            out[n].ray.tfar = fminf(rays[i].tfar, hit.t);
            out[n++].point = k;
        }
    }
    if (!out) ex_die(prog, "out of memory for the proxy tests");
    brt_bvh_free(bvh);
    *tasks = out;
    return n;
}

/* The casts of one kind, alone in a function for callgrind's
** --toggle-collect; returns how many hit. */
static size_t cast_all(const point_set *b, const cast_task *t, size_t n)
{
    size_t i, hits = 0;
    for (i = 0; i < n; i++)
        hits += (size_t)brt_proxy_raycast(b->dag, &b->proxies[t[i].point], &t[i].ray,
                                          t[i].ray.tnear, t[i].ray.tfar, NULL);
    return hits;
}

#if defined(__GNUC__)
#define NOINLINE __attribute__((noinline))
#else
#define NOINLINE
#endif

/* (The two bodies differ so that the compiler does not fold them into one.) */
static NOINLINE size_t cast_culled(const point_set *b, const cast_task *t, size_t n)
{
    return n - cast_all(b, t, n);
}

static NOINLINE size_t cast_hits(const point_set *b, const cast_task *t, size_t n)
{
    return cast_all(b, t, n);
}

/* Puts the culled tasks first; returns their number. */
static size_t split_by_answer(const point_set *b, cast_task *t, size_t n)
{
    size_t i, culled = 0;
    for (i = 0; i < n; i++)
        if (!brt_proxy_raycast(b->dag, &b->proxies[t[i].point], &t[i].ray, t[i].ray.tnear,
                               t[i].ray.tfar, NULL)) {
            cast_task swap = t[culled];
            t[culled++] = t[i];
            t[i] = swap;
        }
    return culled;
}

static void scene_mode(const options *o)
{
    brt_mesh mesh;
    brt_error err;
    point_set b;
    ex_camera cam;
    cast_task *tasks;
    brt_ray *rays = malloc(o->rays * sizeof *rays);
    float bmin[3], bmax[3], eye[3], target[3], fov;
    uint64_t rng = o->seed;
    size_t n, culled, hits;
    double start, culled_s, hit_s;
    uint32_t width, height;
    if (o->rays < 64) ex_die(prog, "--scene needs --rays 64 or more");
    if (!rays) ex_die(prog, "out of memory for %llu rays", (unsigned long long)o->rays);
    ex_check(prog, ex_scene_generate(o->scene, o->scale, 1, &mesh, &err), &err);
    brt_mesh_bounds(&mesh, bmin, bmax);
    ex_scene_camera(o->scene, bmin, bmax, eye, target, &fov);
    /* a 16:9 image of about rays / 2 pixels, one camera ray each */
    height = (uint32_t)ceil(sqrt(o->rays / 2 * 9.0 / 16));
    width = (uint32_t)(o->rays / 2 / height);
    ex_camera_look(&cam, eye, target, fov, width, height);
    build_points(&mesh, o->point_tris, o->res, &b);
    ex_rays_camera(&cam, rays, o->rays / 2, &rng);
    {
        brt_bvh *bvh;
        ex_check(prog, brt_bvh_build(mesh.positions, mesh.indices, mesh.triangle_count, NULL, &bvh), NULL);
        if (!ex_rays_bounce(&mesh, bvh, &cam, rays + o->rays / 2, o->rays - o->rays / 2, &rng))
            ex_die(prog, "%s: no camera ray hits the scene", o->scene);
        brt_bvh_free(bvh);
    }
    n = make_tasks(&mesh, &b, rays, o->rays, &tasks);
    culled = split_by_answer(&b, tasks, n);
    start = ex_cpu_seconds();
    if (cast_culled(&b, tasks, culled) != culled) ex_die(prog, "a culled cast hit on the second try");
    culled_s = ex_cpu_seconds() - start;
    start = ex_cpu_seconds();
    hits = cast_hits(&b, tasks + culled, n - culled);
    hit_s = ex_cpu_seconds() - start;
    if (hits != n - culled) ex_die(prog, "a hit cast missed on the second try");
    printf("\n== %s at scale %g: %u triangles in %u batching points of at most %u, "
           "proxies %u^3, DAG %lu bytes\n", o->scene, o->scale, mesh.triangle_count, b.count,
           o->point_tris, o->res, (unsigned long)brt_svdag_memory_bytes(b.dag));
    printf("rays %llu (half camera, half bounces), proxy tests %lu: culled %lu (%.1f%%), hit %lu\n",
           (unsigned long long)o->rays, (unsigned long)n, (unsigned long)culled,
           n ? 100.0 * culled / n : 0.0, (unsigned long)(n - culled));
    printf("  CPU per culled cast %.0f ns, per hit %.0f ns (instructions: callgrind, "
           "--toggle-collect=cast_culled or cast_hits)\n",
           culled ? 1e9 * culled_s / culled : 0.0, n > culled ? 1e9 * hit_s / (n - culled) : 0.0);
    brt_svdag_free(b.dag);
    free(b.proxies);
    free(b.box);
    free(tasks);
    free(rays);
    brt_mesh_free(&mesh);
}

static void bench_mesh(const char *path, const options *o)
{
    brt_mesh mesh;
    brt_error err;
    double start = brt_seconds();
    ex_check(prog, brt_mesh_load(path, &mesh, &err), &err);
    printf("\n== %s: %u triangles, %u vertices (loaded in %.2f s)\n", path,
           mesh.triangle_count, mesh.vertex_count, brt_seconds() - start);
    if (mesh.triangle_count == 0) ex_die(prog, "%s: the mesh has no triangles", path);
    throughput(&mesh, o);
    if (!o->no_table) memory_table(&mesh);
    brt_mesh_free(&mesh);
}

int main(int argc, char **argv)
{
    static const char *defaults[] = {"bunny_tiny.obj", "bunny.obj.gz", "dragon.obj.gz"};
    options o;
    int i;
    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    parse_options(argc, argv, &o);
    if (o.scene) {
        scene_mode(&o);
        return 0;
    }
    for (i = 0; i < o.mesh_count; i++) bench_mesh(o.meshes[i], &o);
    if (o.mesh_count == 0)
        for (i = 0; i < 3; i++) {
            char buf[512];
            const char *path = shared_mesh(defaults[i], buf, sizeof buf);
            if (path) bench_mesh(path, &o);
            else printf("\n== %s: not found under ../shared/data/meshes, skipped\n", defaults[i]);
        }
    return 0;
}
