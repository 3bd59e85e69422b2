/*
** examples/tutorials/minimal_batched.c -- the batched API of batchrt in one page:
** build a scene file (batching points, their BVH blobs and voxel proxies),
** open it, trace rays through proxies, queues and the geometry cache under a
** memory limit, and check the hits against the direct mode (one BVH in
** memory), byte for byte.  The mesh is a built-in icosahedron cut into
** batching points of two triangles; the scene file goes to $TMPDIR (else
** /tmp) and is removed at the end.  Only the public API of batchrt.h.
**
**   build/minimal_batched
*/
#ifndef _POSIX_C_SOURCE
#define _POSIX_C_SOURCE 200809L   /* mkstemp */
#endif
#include "batchrt.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#define P 1.618034f   /* the golden ratio: an icosahedron's corners */
static float positions[] = {-1, P, 0,  1, P, 0,  -1, -P, 0,  1, -P, 0,
                            0, -1, P,  0, 1, P,  0, -1, -P,  0, 1, -P,
                            P, 0, -1,  P, 0, 1,  -P, 0, -1,  -P, 0, 1};
static uint32_t indices[] = {0, 11, 5,  0, 5, 1,  0, 1, 7,  0, 7, 10,  0, 10, 11,
                             1, 5, 9,  5, 11, 4,  11, 10, 2,  10, 7, 6,  7, 1, 8,
                             3, 9, 4,  3, 4, 2,  3, 2, 6,  3, 6, 8,  3, 8, 9,
                             4, 9, 5,  2, 4, 11,  6, 2, 10,  8, 6, 7,  9, 8, 1};
#define SIDE 16   /* SIDE x SIDE camera rays */

/* Builds, opens and traces the scene file at path; hits[] gets the answers. */
static brt_result trace_batched(const brt_mesh *mesh, const char *path, const brt_ray *rays,
                                brt_hit *hits, brt_stats *stats, brt_error *err)
{
    brt_scene_options build = {0};
    brt_trace_options trace = {0};
    brt_scene *scene;
    brt_result r;
    build.point_tris = 2;         /* ten batching points */
    build.proxy_res = 16;         /* a 16^3 voxel proxy each */
    trace.memory_limit = 16384;   /* the proxies and about three blobs of 4 KiB */
    r = brt_scene_build(mesh, &build, 0, path, err);
    if (r == BRT_OK) r = brt_scene_open(path, &scene, err);
    if (r != BRT_OK) return r;
    r = brt_scene_trace(scene, &trace, rays, SIDE * SIDE, hits, stats, err);
    brt_scene_close(scene);
    return r;
}

int main(int argc, char **argv)
{
    brt_mesh mesh = {positions, indices, 12, 20};
    brt_ray rays[SIDE * SIDE];
    brt_hit hits[SIDE * SIDE], direct[SIDE * SIDE];
    brt_stats stats;
    brt_error err;
    brt_bvh *bvh;
    const char *dir = getenv("TMPDIR") ? getenv("TMPDIR") : "/tmp";
    char path[4096];
    int i, fd, count = 0;
    brt_result r;

    if (argc > 1 && strcmp(argv[1], "--help") != 0) {
        fprintf(stderr, "minimal_batched: takes no arguments (see --help)\n");
        return 1;
    }
    if (argc > 1) {
        printf("usage: build/minimal_batched   (no arguments: traces %d rays through a\n"
               "  scene file of a built-in icosahedron, written to $TMPDIR and removed)\n", SIDE * SIDE);
        return 0;
    }
    /* A pinhole camera at z = 4 looking at the origin; the corners miss. */
    for (i = 0; i < SIDE * SIDE; i++) {
        brt_ray ray = {{0, 0, 4}, {0, 0, -4}, 0, INFINITY};
        ray.dir[0] = 4.0f * ((i % SIDE) + 0.5f) / SIDE - 2.0f;
        ray.dir[1] = 4.0f * ((i / SIDE) + 0.5f) / SIDE - 2.0f;
        rays[i] = ray;
    }
    snprintf(path, sizeof path, "%s/minimal_batched-XXXXXX", dir);
    if ((fd = mkstemp(path)) < 0) {
        perror("minimal_batched: cannot create a temporary file");
        return 1;
    }
    close(fd);
    r = trace_batched(&mesh, path, rays, hits, &stats, &err);
    remove(path);
    if (r != BRT_OK) {
        fprintf(stderr, "minimal_batched: %s\n", err.message);
        return 1;
    }
    /* The direct mode, the reference: one BVH over the whole mesh. */
    if (brt_bvh_build(positions, indices, 20, NULL, &bvh) != BRT_OK) {
        fprintf(stderr, "minimal_batched: out of memory\n");
        return 1;
    }
    for (i = 0; i < SIDE * SIDE; i++) {
        brt_hit_clear(&direct[i]);
        brt_bvh_intersect(bvh, &rays[i], &direct[i]);
        count += hits[i].prim != BRT_NO_PRIM;
    }
    brt_bvh_free(bvh);
    printf("scene: %u triangles in %u batching points, proxies %u bytes\n",
           mesh.triangle_count, (unsigned)stats.batching_points, (unsigned)stats.proxy_bytes);
    printf("rays: %d, hits %d, misses %d\n", SIDE * SIDE, count, SIDE * SIDE - count);
    printf("proxy tests %u, culled %u; queued visits %u; loads %u, %u bytes read (limit %u)\n",
           (unsigned)stats.proxy_tests, (unsigned)stats.proxy_culled,
           (unsigned)stats.queued_visits, (unsigned)stats.batch_loads,
           (unsigned)stats.disk_bytes_read, (unsigned)stats.memory_limit);
    i = memcmp(hits, direct, sizeof hits) == 0;
    printf("batched hits %s the direct mode's, byte for byte\n", i ? "equal" : "DIFFER from");
    return i ? 0 : 1;
}
