/*
** examples/tools/closed.c -- how much of a mesh inner proxies can use: the
** triangles that lie in closed components (svdag.c, "Inner proxies":
** components joined by exactly equal vertex positions in which every edge
** is used an even number of times, no triangle degenerate).  The whole
** mesh is one component set here; a scene build judges each bucket (up to
** 1.68 M triangles) alone, so a closed component that a bucket boundary
** cuts counts here but gets no inner voxels there.
**
**   build/closed MESH|SCENE [--scale S] [--seed N]
**
** SCENE is a built-in scene name (crown, landscape, island: the meshes of
** mkscene, the landscape and the island baked from their instances).  A
** pbrt file is flattened (ex_input_load_mesh).
*/
#include "batchrt.h"
#include "common.h"
#include "input.h"
#include "scenes.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int main(int argc, char **argv)
{
    const char *prog = "closed";
    double scale = 1.0;
    uint64_t seed = 1;
    brt_solids *solids = NULL;
    float *corners;
    uint32_t t;
    brt_mesh mesh;
    brt_error err;
    brt_result r;
    int i;
    if (argc < 2 || strcmp(argv[1], "--help") == 0) {
        printf("usage: build/closed MESH|SCENE [--scale S] [--seed N]\n"
               "  prints the triangles in closed components (inner proxies' material)\n");
        return argc < 2;
    }
    for (i = 2; i < argc; i++) {
        if (strcmp(argv[i], "--scale") == 0)
            scale = ex_parse_double(prog, "--scale", ex_option_value(prog, argc, argv, &i), 0.001,
                                    EX_SCENE_MAX_SCALE);
        else if (strcmp(argv[i], "--seed") == 0)
            seed = ex_parse_u64(prog, "--seed", ex_option_value(prog, argc, argv, &i), 0, UINT64_MAX);
        else
            ex_unknown_option(prog, argv[i]);
    }
    r = ex_scene_generate(argv[1], scale, seed, &mesh, &err);
    if (r == BRT_EARG) ex_input_load_mesh(prog, argv[1], &mesh);   /* a pbrt file flattened */
    else ex_check(prog, r, &err);
    corners = malloc((9 * (size_t)mesh.triangle_count + 1) * sizeof *corners);
    if (!corners) ex_die(prog, "out of memory for %u triangles", mesh.triangle_count);
    for (t = 0; t < mesh.triangle_count; t++)
        for (i = 0; i < 3; i++)
            memcpy(corners + 9 * (size_t)t + 3 * i, mesh.positions + 3 * (size_t)mesh.indices[3 * (size_t)t + i],
                   3 * sizeof *corners);
    r = brt_solids_build(corners, 9, mesh.triangle_count, &solids);
    if (r != BRT_OK) ex_die(prog, "%s: %s", argv[1], brt_result_string(r));
    printf("%s: %u triangles, %u in closed components (%.1f %%)\n", argv[1], mesh.triangle_count,
           brt_solids_triangles(solids),
           mesh.triangle_count ? 100.0 * brt_solids_triangles(solids) / mesh.triangle_count : 0.0);
    brt_solids_free(solids);
    free(corners);
    brt_mesh_free(&mesh);
    return 0;
}
