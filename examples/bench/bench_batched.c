/*
** examples/bench/bench_batched.c -- the out-of-core benchmark (README, Benchmarks)
** (`make bench-batched`): what proxies save when geometry is on disk,
** what batching costs in core, and how fast preprocessing is.
**
**   build/bench_batched [MESH | SCENE] [--scale S] [--rays N] [--limit P]
**                       [--point-tris N] [--proxy-res R] [--scene FILE]
**
** By default: the built-in landscape at scale 0.8 (baked from its
** instances: about 5 million triangles), 1M rays (half camera rays from the scene's default view, half
** bounce rays from their hits), the memory limit at 25 % of the geometry
** bytes, the scene file's pages dropped from the OS cache before each
** out-of-core run so that the disk is read, not the OS page cache.
**
** Prints one table; every batched run is also compared with the direct
** hits, byte for byte (a benchmark that returned wrong hits would be
** meaningless).  Figures only; nothing here passes or fails.
*/
#include "rays.h"
#include "scenes.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static const char *const prog = "bench_batched";

typedef struct options {
    const char *input;          /* mesh file or built-in scene name */
    double scale;
    uint64_t rays, point_tris, res;
    double limit_percent;
    const char *scene;
} options;

static void usage(void)
{
    printf("usage: build/bench_batched [MESH | SCENE] [options]\n"
           "Out-of-core batched tracing with and without voxel proxies, against direct\n"
           "tracing in memory.  SCENE is a built-in scene (crown, landscape, island).\n"
           "\n"
           "  --scale S        size of a built-in scene (default 0.8: about 5M triangles)\n"
           "  --rays N         rays, half camera and half bounce (default 1000000)\n"
           "  --limit P        memory limit in percent of the geometry bytes (default 25)\n"
           "  --point-tris N   triangles per batching point (default 100000)\n"
           "  --proxy-res R    proxy resolution (default 128)\n"
           "  --scene FILE     where to write the scene file (default /tmp)\n"
           "  --help           this text\n");
}

static void parse_options(int argc, char **argv, options *o)
{
    int i;
    memset(o, 0, sizeof *o);
    o->input = "landscape";
    o->scale = 0.8;
    o->rays = 1000000;
    o->point_tris = 100000;
    o->res = 128;
    o->limit_percent = 25;
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (strcmp(a, "--scale") == 0)
            o->scale = ex_parse_double(prog, a, ex_option_value(prog, argc, argv, &i), 0.01, EX_SCENE_MAX_SCALE);
        else if (strcmp(a, "--rays") == 0)
            o->rays = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 2, UINT32_MAX);
        else if (strcmp(a, "--limit") == 0)
            o->limit_percent = ex_parse_double(prog, a, ex_option_value(prog, argc, argv, &i), 0.1, 1000);
        else if (strcmp(a, "--point-tris") == 0)
            o->point_tris = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 1, UINT32_MAX);
        else if (strcmp(a, "--proxy-res") == 0)
            o->res = ex_parse_resolution(prog, a, ex_option_value(prog, argc, argv, &i));
        else if (strcmp(a, "--scene") == 0) o->scene = ex_option_value(prog, argc, argv, &i);
        else if (a[0] == '-') ex_unknown_option(prog, a);
        else o->input = a;
    }
}

static void load_input(const options *o, brt_mesh *mesh)
{
    brt_error err;
    if (ex_scene_is_builtin(o->input))
        ex_check(prog, ex_scene_generate(o->input, o->scale, 1, mesh, &err), &err);
    else
        ex_check(prog, brt_mesh_load(o->input, mesh, &err), &err);
}

/* Half camera rays from the scene's view, half bounce rays from them. */
static brt_ray *make_rays(const options *o, const brt_mesh *mesh, const brt_bvh *bvh)
{
    size_t half = (size_t)o->rays / 2, width = 1024;
    brt_ray *rays = malloc(2 * half * sizeof *rays);
    float bmin[3], bmax[3], eye[3], target[3], fov = (float)EX_CAMERA_FOV;
    uint64_t rng = 7;
    ex_camera cam;
    if (!rays) ex_die(prog, "out of memory for rays");
    brt_mesh_bounds(mesh, bmin, bmax);
    if (ex_scene_is_builtin(o->input)) {
        ex_scene_camera(o->input, bmin, bmax, eye, target, &fov);
        ex_camera_look(&cam, eye, target, fov, (uint32_t)width, (uint32_t)((half + width - 1) / width));
    } else {
        ex_camera_fit(&cam, bmin, bmax, (uint32_t)width, (uint32_t)((half + width - 1) / width));
    }
    ex_rays_camera(&cam, rays, half, &rng);
    if (!ex_rays_bounce(mesh, bvh, &cam, rays + half, half, &rng))
        ex_die(prog, "%s: no camera ray hits the scene", o->input);
    return rays;
}

static void trace_direct(const brt_bvh *bvh, const brt_ray *rays, size_t n, brt_hit *hits,
                         double *seconds)
{
    double start = brt_seconds();
    size_t i;
    for (i = 0; i < n; i++) {
        brt_hit_clear(&hits[i]);
        brt_bvh_intersect(bvh, &rays[i], &hits[i]);
    }
    *seconds = brt_seconds() - start;
}

static void print_row(const char *label, const brt_stats *s, double direct_seconds,
                      int identical)
{
    printf("| %-26s | %8.2f | %7.3f | %9.1f | %6llu | %9llu | %9llu | %5.2fx | %s |\n", label,
           s->seconds, (double)s->rays / s->seconds * 1e-6, (double)s->disk_bytes_read / 1048576.0,
           (unsigned long long)s->batch_loads, (unsigned long long)s->visits,
           (unsigned long long)s->proxy_culled, direct_seconds / s->seconds,
           identical ? "yes" : "NO");
}

static void run_batched(brt_scene *scene, const char *label, uint64_t limit, int no_proxy,
                        int cold, const brt_ray *rays, size_t n, const brt_hit *direct,
                        double direct_seconds, brt_stats *stats)
{
    brt_trace_options opt;
    brt_hit *hits = malloc(n * sizeof *hits);
    brt_error err;
    if (!hits) ex_die(prog, "out of memory for hits");
    memset(&opt, 0, sizeof opt);
    opt.memory_limit = limit;
    opt.no_proxy = no_proxy;
    opt.drop_os_cache = cold;
    opt.rays_in_flight = (uint32_t)n;
    ex_check(prog, brt_scene_trace(scene, &opt, rays, n, hits, stats, &err), &err);
    print_row(label, stats, direct_seconds, memcmp(hits, direct, n * sizeof *hits) == 0);
    free(hits);
}

int main(int argc, char **argv)
{
    options o;
    brt_mesh mesh;
    brt_bvh *bvh;
    brt_ray *rays;
    brt_hit *direct;
    brt_scene *scene;
    brt_scene_options scene_opt;
    brt_stats stats, with, without;
    brt_error err;
    char default_scene[256];
    double start, build_seconds, direct_seconds, bvh_seconds;
    uint64_t limit;
    size_t n;

    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    parse_options(argc, argv, &o);
    load_input(&o, &mesh);
    start = brt_seconds();
    ex_check(prog, brt_bvh_build(mesh.positions, mesh.indices, mesh.triangle_count, NULL, &bvh), NULL);
    bvh_seconds = brt_seconds() - start;
    rays = make_rays(&o, &mesh, bvh);
    n = (size_t)o.rays / 2 * 2;
    direct = malloc(n * sizeof *direct);
    if (!direct) ex_die(prog, "out of memory for hits");
    trace_direct(bvh, rays, n, direct, &direct_seconds);
    brt_bvh_free(bvh);

    if (!o.scene) {
        snprintf(default_scene, sizeof default_scene, "/tmp/bench_batched-%ld.brs", (long)getpid());
        o.scene = default_scene;
    }
    memset(&scene_opt, 0, sizeof scene_opt);
    scene_opt.point_tris = (uint32_t)o.point_tris;
    scene_opt.proxy_res = (uint32_t)o.res;
    start = brt_seconds();
    ex_check(prog, brt_scene_build(&mesh, &scene_opt, 0, o.scene, &err), &err);
    build_seconds = brt_seconds() - start;
    ex_check(prog, brt_scene_open(o.scene, &scene, &err), &err);

    printf("%s: %u triangles, %u batching points of <= %llu, proxies %llu^3\n", o.input,
           mesh.triangle_count, brt_scene_point_count(scene), (unsigned long long)o.point_tris,
           (unsigned long long)o.res);
    printf("preprocessing: %.2f s, %.2f M triangles/s (direct BVH build: %.2f s)\n", build_seconds,
           mesh.triangle_count / build_seconds * 1e-6, bvh_seconds);
    printf("direct, in memory: %zu rays in %.2f s, %.3f Mrays/s\n\n", n, direct_seconds,
           n / direct_seconds * 1e-6);
    printf("| run                        | time (s) | Mrays/s | read (MiB) |  loads | visits    | culled    | vs direct | same hits |\n");
    printf("|---|---:|---:|---:|---:|---:|---:|---:|---|\n");
    run_batched(scene, "in core, no proxies", 0, 1, 0, rays, n, direct, direct_seconds, &stats);
    run_batched(scene, "in core, proxies", 0, 0, 0, rays, n, direct, direct_seconds, &stats);
    limit = (uint64_t)((double)stats.geometry_bytes * o.limit_percent / 100.0);
    run_batched(scene, "out of core, no proxies", limit, 1, 1, rays, n, direct, direct_seconds, &without);
    run_batched(scene, "out of core, proxies", limit, 0, 1, rays, n, direct, direct_seconds, &with);
    printf("\nmemory limit %.1f MiB (%.0f %% of %.1f MiB geometry; proxies take %.2f MiB of it)\n",
           limit / 1048576.0, o.limit_percent, stats.geometry_bytes / 1048576.0,
           with.proxy_bytes / 1048576.0);
    printf("proxies: disk bytes x%.2f, loads x%.2f, visits x%.2f, time x%.2f\n",
           (double)with.disk_bytes_read / (double)without.disk_bytes_read,
           (double)with.batch_loads / (double)without.batch_loads,
           (double)with.visits / (double)without.visits, with.seconds / without.seconds);
    brt_scene_close(scene);
    if (o.scene == default_scene) unlink(default_scene);
    free(direct);
    free(rays);
    brt_mesh_free(&mesh);
    return 0;
}
