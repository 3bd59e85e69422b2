/*
** examples/bench_svdag.c -- what the conservative voxel proxies (svdag.c,
** after Molenaar and Eisemann 2020) cost and how fast they answer.
** Prints figures, never pass/fail.
**
** Usage: build/bench_svdag [MESH...] [--rays N] [--res R] [--seed S] [--no-table]
**   MESH defaults to bunny_tiny, bunny and dragon from ../shared/data/meshes
**   (the .gz ones unpacked with gzip into /tmp), whichever are present.
** For each mesh:
**   - throughput on the same rays (half camera rays, half rays from a
**     sphere around the mesh aimed into its box): the proxy ray cast at
**     --res beside the BVH's closest hit, single thread, in CPU time (the
**     process's own, so that other jobs on a shared machine do not count),
**     and how many BVH hits the proxy missed (must be 0) or added (false hits);
**   - voxelization and DAG build time, and DAG bytes, at res 16..512
**     (the paper's Fig. 2, left), as a Markdown table.
*/
#include "common.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>

static const char *const prog = "bench_svdag";

typedef struct options {
    const char *meshes[16];
    int mesh_count;
    uint64_t rays, seed;
    uint32_t res;
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
           "  --res R     proxy resolution of the throughput run (default 128)\n"
           "  --seed S    ray generator seed (default 1)\n"
           "  --no-table  throughput only, no build/memory table\n"
           "  --help      this text\n");
}

static void parse_options(int argc, char **argv, options *o)
{
    int i;
    memset(o, 0, sizeof *o);
    o->rays = 1000000;
    o->res = 128;
    o->seed = 1;
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (strcmp(a, "--rays") == 0)
            o->rays = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 1, 100000000);
        else if (strcmp(a, "--seed") == 0)
            o->seed = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 0, UINT64_MAX);
        else if (strcmp(a, "--no-table") == 0) o->no_table = 1;
        else if (strcmp(a, "--res") == 0)
            o->res = ex_parse_resolution(prog, a, ex_option_value(prog, argc, argv, &i));
        else if (a[0] == '-' && a[1] != 0) ex_die(prog, "unknown option '%s' (see --help)", a);
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
static double cpu_seconds(void)
{
    return (double)clock() / CLOCKS_PER_SEC;
}

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
    start = cpu_seconds();
    for (n = 0; n < o->rays; n++) {
        brt_hit_clear(&hits[n]);
        brt_bvh_intersect(bvh, &rays[n], &hits[n]);
    }
    bvh_seconds = cpu_seconds() - start;
    start = cpu_seconds();
    for (n = 0; n < o->rays; n++) {
        float t;
        int got = brt_proxy_raycast(dag, &proxy, &rays[n], 0, INFINITY, &t);
        proxy_hits += got;
        /* Stored in the ray's tnear slot so the check below is outside the timing. */
        rays[n].tnear = got ? t : -INFINITY;
    }
    proxy_seconds = cpu_seconds() - start;
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
