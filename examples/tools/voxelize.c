/*
** examples/tools/voxelize.c -- build the conservative voxel proxy of a mesh (the
** contribution of Molenaar and Eisemann 2020) and show what it costs and
** what it looks like.
**
**   build/voxelize MESH [--proxy-res 128] [--stats S.json] [--out PROXY.png]
**
** Prints the voxels set, the nodes of the sparse voxel octree, the nodes
** and bytes of its DAG (Kampe et al. 2013), and the build time; then the
** same for the mesh split into 8 octant proxies in one shared pool, so the
** sharing of identical sub-blocks across proxies shows.  --out renders the
** proxy (ray cast through the DAG) beside the mesh (BVH closest hit) from
** the same camera, shaded by depth on one scale, so a reader sees that
** the proxy covers every surface and by how much it overshoots.
** Every output is computed before any file is written, and written
** atomically: a failed run leaves nothing behind.
*/
#include "common.h"
#include "input.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static const char *const prog = "voxelize";

typedef struct options {
    const char *mesh, *stats, *out;
    uint32_t res, image;
} options;

/* What one proxy (or a set of proxies in one pool) costs. */
typedef struct proxy_figures {
    uint64_t voxels, svo_nodes;
    uint32_t dag_nodes;
    size_t dag_bytes;
    double seconds;
} proxy_figures;

static void usage(void)
{
    printf("usage: build/voxelize MESH [options]\n"
           "Voxelizes MESH (OBJ or PLY) conservatively into a res^3 grid fitted to its\n"
           "bounds, builds the sparse voxel DAG and prints voxels, SVO nodes, DAG nodes\n"
           "and bytes and the build time, alone and as 8 octant proxies sharing a pool.\n"
           "\n"
           "  --proxy-res R  grid resolution, a power of two in 2..1024 (default 128)\n"
           "  --stats FILE   write the figures as JSON (triangles, resolution, voxels,\n"
           "                 svo_nodes, dag_nodes, dag_bytes, seconds, octant_*)\n"
           "  --out FILE     write a PNG: the proxy ray cast through the DAG (left) and\n"
           "                 the mesh traced with the BVH (right), same camera, depth shaded\n"
           "  --size N       height of each half of the PNG in pixels (default 384)\n"
           "  --help         this text\n"
           "\n"
           "Exit status 0 on success, 1 on bad input (nothing is written then).\n");
}

static void parse_options(int argc, char **argv, options *o)
{
    int i;
    memset(o, 0, sizeof *o);
    o->res = 128;
    o->image = 384;
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (strcmp(a, "--proxy-res") == 0)
            o->res = ex_parse_resolution(prog, a, ex_option_value(prog, argc, argv, &i));
        else if (strcmp(a, "--size") == 0)
            o->image = (uint32_t)ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 16, 4096);
        else if (strcmp(a, "--stats") == 0) o->stats = ex_option_value(prog, argc, argv, &i);
        else if (strcmp(a, "--out") == 0) o->out = ex_option_value(prog, argc, argv, &i);
        else if (a[0] == '-' && a[1] != 0) ex_unknown_option(prog, a);
        else if (!o->mesh) o->mesh = a;
        else ex_die(prog, "unexpected argument '%s' (see --help)", a);
    }
    if (!o->mesh) ex_die(prog, "expected MESH (see --help)");
}

/* Bounds of the triangles given by count index triples. */
static void triangle_bounds(const brt_mesh *mesh, const uint32_t *indices,
                            uint32_t count, float bmin[3], float bmax[3])
{
    uint32_t k;
    int i;
    for (i = 0; i < 3; i++) { bmin[i] = INFINITY; bmax[i] = -INFINITY; }
    for (k = 0; k < 3 * count; k++)
        for (i = 0; i < 3; i++) {
            float x = mesh->positions[3 * (size_t)indices[k] + i];
            bmin[i] = fminf(bmin[i], x);
            bmax[i] = fmaxf(bmax[i], x);
        }
}

/* Voxelizes triangles (given by indices) at res into a new proxy in dag;
** adds the voxels, SVO nodes and time to *f. */
static void add_proxy(const brt_mesh *mesh, const uint32_t *indices, uint32_t count,
                      uint32_t res, brt_svdag *dag, brt_proxy *proxy, proxy_figures *f)
{
    brt_grid grid;
    float bmin[3], bmax[3];
    double start = brt_seconds();
    triangle_bounds(mesh, indices, count, bmin, bmax);
    ex_check(prog, brt_grid_init(&grid, bmin, bmax, res), NULL);
    ex_check(prog, brt_voxelize(&grid, mesh->positions, indices, count), NULL);
    ex_check(prog, brt_svdag_add(dag, &grid, proxy), NULL);
    f->seconds += brt_seconds() - start;
    f->voxels += brt_grid_count(&grid);
    f->svo_nodes += brt_svdag_svo_nodes(dag, proxy);
    brt_grid_free(&grid);
}

static void pool_figures(const brt_svdag *dag, proxy_figures *f)
{
    f->dag_nodes = brt_svdag_node_count(dag);
    f->dag_bytes = brt_svdag_memory_bytes(dag);
}

/* The mesh's triangles regrouped by the octant of their centroid. */
static uint32_t *octant_order(const brt_mesh *mesh, uint32_t first[9])
{
    float bmin[3], bmax[3];
    uint32_t t, count[8] = {0}, *order;
    unsigned char *octant = malloc(mesh->triangle_count + 1);
    int o;
    order = malloc(3 * (size_t)mesh->triangle_count * sizeof *order + 1);
    if (!octant || !order) ex_die(prog, "%s: out of memory", "octants");
    brt_mesh_bounds(mesh, bmin, bmax);
    for (t = 0; t < mesh->triangle_count; t++) {
        int i, k, code = 0;
        for (i = 0; i < 3; i++) {
            float c = 0, mid = 0.5f * (bmin[i] + bmax[i]);
            for (k = 0; k < 3; k++) c += mesh->positions[3 * (size_t)mesh->indices[3 * (size_t)t + k] + i];
            code |= (c > 3 * mid) << i;
        }
        octant[t] = (unsigned char)code;
        count[code]++;
    }
    first[0] = 0;
    for (o = 0; o < 8; o++) first[o + 1] = first[o] + count[o];
    memset(count, 0, sizeof count);
    for (t = 0; t < mesh->triangle_count; t++) {
        uint32_t at = first[octant[t]] + count[octant[t]]++;
        memcpy(order + 3 * (size_t)at, mesh->indices + 3 * (size_t)t, 3 * sizeof *order);
    }
    free(octant);
    return order;
}

/* 8 octant proxies in one shared pool, and the same 8 in separate pools
** (the bytes they would take without sharing across proxies). */
static void octant_proxies(const brt_mesh *mesh, uint32_t res, proxy_figures *shared,
                           size_t *separate_bytes)
{
    uint32_t first[9], *order = octant_order(mesh, first);
    brt_svdag *pool, *alone;
    int o;
    memset(shared, 0, sizeof *shared);
    *separate_bytes = 0;
    ex_check(prog, brt_svdag_create(&pool), NULL);
    for (o = 0; o < 8; o++) {
        brt_proxy proxy;
        proxy_figures unused = {0, 0, 0, 0, 0};
        uint32_t n = first[o + 1] - first[o];
        if (n == 0) continue;
        add_proxy(mesh, order + 3 * (size_t)first[o], n, res, pool, &proxy, shared);
        ex_check(prog, brt_svdag_create(&alone), NULL);
        add_proxy(mesh, order + 3 * (size_t)first[o], n, res, alone, &proxy, &unused);
        *separate_bytes += brt_svdag_memory_bytes(alone);
        brt_svdag_free(alone);
    }
    pool_figures(pool, shared);
    brt_svdag_free(pool);
    free(order);
}

/* ===================================================================== */
/* The picture                                                           */
/* ===================================================================== */

typedef struct camera {
    float eye[3], forward[3], right[3], up[3];
    float near_t, far_t;   /* depth range for shading */
} camera;

static void normalize(float v[3])
{
    float n = sqrtf(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    v[0] /= n; v[1] /= n; v[2] /= n;
}

/* Looks at the box centre from above and to the side, 40 degrees wide. */
static void camera_setup(const float bmin[3], const float bmax[3], camera *c)
{
    float centre[3], radius = 0, scale, from[3] = {0.55f, 0.45f, 0.7f};
    int i;
    normalize(from);
    for (i = 0; i < 3; i++) {
        centre[i] = 0.5f * (bmin[i] + bmax[i]);
        radius += (bmax[i] - bmin[i]) * (bmax[i] - bmin[i]);
    }
    radius = 0.5f * sqrtf(radius);
    scale = radius / sinf(0.35f);   /* the bounding sphere fills the view */
    for (i = 0; i < 3; i++) {
        c->eye[i] = centre[i] + from[i] * scale;
        c->forward[i] = centre[i] - c->eye[i];
    }
    normalize(c->forward);
    c->right[0] = -c->forward[2]; c->right[1] = 0; c->right[2] = c->forward[0];
    normalize(c->right);
    c->up[0] = c->right[1] * c->forward[2] - c->right[2] * c->forward[1];
    c->up[1] = c->right[2] * c->forward[0] - c->right[0] * c->forward[2];
    c->up[2] = c->right[0] * c->forward[1] - c->right[1] * c->forward[0];
    c->near_t = scale - radius;
    c->far_t = scale + radius;
}

static brt_ray camera_ray(const camera *c, uint32_t x, uint32_t y, uint32_t size)
{
    brt_ray ray;
    float px = (2.0f * (x + 0.5f) / size - 1) * 0.364f, py = (1 - 2.0f * (y + 0.5f) / size) * 0.364f;
    int i;
    for (i = 0; i < 3; i++) {
        ray.org[i] = c->eye[i];
        ray.dir[i] = c->forward[i] + px * c->right[i] + py * c->up[i];
    }
    ray.tnear = 0;
    ray.tfar = INFINITY;
    return ray;
}

/* Near is bright; the proxy in amber, the mesh in grey, misses dark blue. */
static void shade(unsigned char *px, int hit, float t, const camera *c, const float tint[3])
{
    float depth = (t - c->near_t) / (c->far_t - c->near_t), light;
    int i;
    if (!hit) { px[0] = 20; px[1] = 24; px[2] = 40; return; }
    light = 1 - 0.8f * fminf(fmaxf(depth, 0), 1);
    for (i = 0; i < 3; i++) px[i] = (unsigned char)(255 * light * tint[i]);
}

static unsigned char *render(const brt_mesh *mesh, const brt_svdag *dag,
                             const brt_proxy *proxy, uint32_t size)
{
    static const float amber[3] = {1, 0.7f, 0.3f}, grey[3] = {0.9f, 0.9f, 0.9f};
    unsigned char *rgb = malloc(6 * (size_t)size * size);
    float bmin[3], bmax[3];
    brt_bvh *bvh;
    camera cam;
    uint32_t x, y;
    if (!rgb) ex_die(prog, "%s: out of memory", "image");
    brt_mesh_bounds(mesh, bmin, bmax);
    camera_setup(bmin, bmax, &cam);
    ex_check(prog, brt_bvh_build(mesh->positions, mesh->indices, mesh->triangle_count, NULL, &bvh), NULL);
    for (y = 0; y < size; y++)
        for (x = 0; x < size; x++) {
            brt_ray ray = camera_ray(&cam, x, y, size);
            unsigned char *row = rgb + 3 * (size_t)y * 2 * size;
            brt_hit hit;
            float t;
            int got = brt_proxy_raycast(dag, proxy, &ray, 0, INFINITY, &t);
            shade(row + 3 * x, got, t, &cam, amber);
            brt_hit_clear(&hit);
            brt_bvh_intersect(bvh, &ray, &hit);
            shade(row + 3 * (size + x), hit.prim != BRT_NO_PRIM, hit.t, &cam, grey);
        }
    brt_bvh_free(bvh);
    return rgb;
}

/* ===================================================================== */
/* Output                                                                */
/* ===================================================================== */

static void print_figures(const char *label, const proxy_figures *f)
{
    printf("%-22s %12llu %12llu %12u %14lu %10.3f\n", label, (unsigned long long)f->voxels,
           (unsigned long long)f->svo_nodes, f->dag_nodes, (unsigned long)f->dag_bytes, f->seconds);
}

static char *stats_json(const brt_mesh *mesh, uint32_t res, const proxy_figures *alone,
                        const proxy_figures *octants, size_t separate_bytes, size_t *size)
{
    char *json = malloc(1024);
    int n;
    if (!json) ex_die(prog, "%s: out of memory", "stats");
    n = snprintf(json, 1024,
                 "{\n  \"triangles\": %u,\n  \"resolution\": %u,\n  \"voxels\": %llu,\n"
                 "  \"svo_nodes\": %llu,\n  \"dag_nodes\": %u,\n  \"dag_bytes\": %lu,\n"
                 "  \"seconds\": %.6f,\n  \"octant_voxels\": %llu,\n  \"octant_svo_nodes\": %llu,\n"
                 "  \"octant_dag_nodes\": %u,\n  \"octant_dag_bytes\": %lu,\n"
                 "  \"octant_dag_bytes_unshared\": %lu,\n  \"octant_seconds\": %.6f,\n"
                 "  \"peak_rss_bytes\": %llu\n}\n",
                 mesh->triangle_count, res, (unsigned long long)alone->voxels,
                 (unsigned long long)alone->svo_nodes, alone->dag_nodes,
                 (unsigned long)alone->dag_bytes, alone->seconds,
                 (unsigned long long)octants->voxels, (unsigned long long)octants->svo_nodes,
                 octants->dag_nodes, (unsigned long)octants->dag_bytes,
                 (unsigned long)separate_bytes, octants->seconds,
                 (unsigned long long)brt_peak_rss_bytes());
    *size = (size_t)n;
    return json;
}

int main(int argc, char **argv)
{
    options o;
    brt_error err;
    brt_mesh mesh;
    brt_svdag *dag;
    brt_proxy proxy;
    proxy_figures alone = {0, 0, 0, 0, 0}, octants;
    size_t separate_bytes, json_size = 0, png_size = 0;
    unsigned char *png = NULL;
    char *json = NULL;

    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    parse_options(argc, argv, &o);
    ex_catch_interrupts();   /* polled between the phases; a failed load reports it (ex_check) */
    ex_input_load_mesh(prog, o.mesh, &mesh);   /* a pbrt file flattened */
    if (mesh.triangle_count == 0) ex_die(prog, "%s: the mesh has no triangles", o.mesh);

    ex_check(prog, brt_svdag_create(&dag), NULL);
    add_proxy(&mesh, mesh.indices, mesh.triangle_count, o.res, dag, &proxy, &alone);
    pool_figures(dag, &alone);
    octant_proxies(&mesh, o.res, &octants, &separate_bytes);
    if (ex_interrupted()) ex_die_interrupted(prog);

    if (o.out) {
        unsigned char *rgb = render(&mesh, dag, &proxy, o.image);
        ex_check(prog, ex_png_encode_rgb(2 * (int)o.image, (int)o.image, rgb, &png, &png_size), NULL);
        free(rgb);
    }
    if (o.stats) json = stats_json(&mesh, o.res, &alone, &octants, separate_bytes, &json_size);

    printf("%s: %u triangles, grid %u^3\n", o.mesh, mesh.triangle_count, o.res);
    printf("%-22s %12s %12s %12s %14s %10s\n", "", "voxels", "svo nodes", "dag nodes", "dag bytes", "seconds");
    print_figures("one proxy", &alone);
    print_figures("8 octants, one pool", &octants);
    printf("8 octants, 8 pools would take %lu bytes (sharing saves %.1f%%)\n",
           (unsigned long)separate_bytes,
           separate_bytes ? 100.0 * (1.0 - (double)octants.dag_bytes / separate_bytes) : 0.0);

    if (ex_interrupted()) ex_die_interrupted(prog);
    if (png) ex_check(prog, brt_write_file_atomic(o.out, png, png_size, &err), &err);
    if (json && brt_write_file_atomic(o.stats, json, json_size, &err) != BRT_OK) {
        if (png) unlink(o.out);   /* no partial output */
        ex_check(prog, BRT_EIO, &err);
    }
    free(png);
    free(json);
    brt_svdag_free(dag);
    brt_mesh_free(&mesh);
    return 0;
}
