/*
** examples/closed.c -- how much of a mesh inner proxies can use: the
** triangles that lie in closed components (svdag.c, "Inner proxies":
** components joined by exactly equal vertex positions in which every edge
** is used an even number of times, no triangle degenerate).  The whole
** mesh is one component set here; inside a scene file each batching point
** is judged alone, so a closed component that a batching point cuts counts
** here but gets no inner voxels there.
**
**   build/closed MESH|SCENE [--scale S] [--seed N]
**
** SCENE is a built-in scene name (crown, landscape, island).
*/
#include "batchrt.h"
#include "common.h"
#include "scenes.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int main(int argc, char **argv)
{
    const char *prog = "closed";
    double scale = 1.0;
    uint64_t seed = 1;
    float lo[3], hi[3];
    uint32_t closed = 0;
    brt_grid grid;
    brt_mesh mesh;
    brt_error err;
    brt_result r;
    int i;
    if (argc < 2 || strcmp(argv[1], "--help") == 0) {
        printf("usage: build/closed MESH|SCENE [--scale S] [--seed N]\n"
               "  prints the triangles in closed components (inner proxies' material)\n");
        return argc < 2;
    }
    for (i = 2; i + 1 < argc; i += 2) {
        if (strcmp(argv[i], "--scale") == 0) scale = atof(argv[i + 1]);
        else if (strcmp(argv[i], "--seed") == 0) seed = strtoull(argv[i + 1], NULL, 10);
        else ex_die(prog, "unknown option '%s'", argv[i]);
    }
    if (i != argc) ex_die(prog, "option '%s' needs a value", argv[i]);
    r = ex_scene_generate(argv[1], scale, seed, &mesh, &err);
    if (r == BRT_EARG) r = brt_mesh_load(argv[1], &mesh, &err);
    ex_check(prog, r, &err);
    brt_mesh_bounds(&mesh, lo, hi);
    /* The smallest grid: only the count is wanted, not the voxels. */
    r = brt_grid_init(&grid, lo, hi, 2);
    if (r == BRT_OK)
        r = brt_voxelize_inner(&grid, mesh.positions, mesh.indices, mesh.triangle_count, &closed);
    if (r != BRT_OK) ex_die(prog, "%s: %s", argv[1], brt_result_string(r));
    printf("%s: %u triangles, %u in closed components (%.1f %%)\n", argv[1], mesh.triangle_count,
           closed, mesh.triangle_count ? 100.0 * closed / mesh.triangle_count : 0.0);
    brt_grid_free(&grid);
    brt_mesh_free(&mesh);
    return 0;
}
