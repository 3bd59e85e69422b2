/*
** examples/tutorials/minimal.c -- the smallest complete use of batchrt: load a mesh
** (or make a two-triangle quad), build a BVH, trace a few rays, print hits.
**
**   build/minimal [MESH]
*/
#include "batchrt.h"

#include <math.h>
#include <stdio.h>
#include <string.h>

/* The unit quad [0,1]^2 at z = 0 as two triangles sharing the diagonal. */
static float quad_positions[] = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0};
static uint32_t quad_indices[] = {0, 1, 2, 0, 2, 3};

int main(int argc, char **argv)
{
    brt_mesh mesh = {quad_positions, quad_indices, 4, 2};
    brt_error err;
    brt_bvh *bvh;
    float bmin[3], bmax[3];
    int i;

    if (argc > 1 && strcmp(argv[1], "--help") == 0) {
        printf("usage: build/minimal [MESH]   traces 5 rays down the z axis\n");
        return 0;
    }
    if (argc > 1 && brt_mesh_load(argv[1], &mesh, &err) != BRT_OK) {
        fprintf(stderr, "minimal: %s\n", err.message);
        return 1;
    }
    if (brt_bvh_build(mesh.positions, mesh.indices, mesh.triangle_count, NULL, &bvh) != BRT_OK) {
        fprintf(stderr, "minimal: out of memory\n");
        return 1;
    }
    /* Five rays straight down (-z) from above the mesh, along the diagonal
    ** of its box that crosses the quad's shared edge. */
    brt_mesh_bounds(&mesh, bmin, bmax);
    for (i = 0; i < 5; i++) {
        float s = (i + 0.5f) / 5;
        brt_ray ray = {{0, 0, 0}, {0, 0, -1}, 0, INFINITY};
        brt_hit hit;
        ray.org[0] = bmin[0] + s * (bmax[0] - bmin[0]);
        ray.org[1] = bmax[1] - s * (bmax[1] - bmin[1]);
        ray.org[2] = bmax[2] + 1;
        brt_hit_clear(&hit);
        brt_bvh_intersect(bvh, &ray, &hit);
        if (hit.prim == BRT_NO_PRIM)
            printf("ray %d from (%g, %g, %g): miss\n", i, ray.org[0], ray.org[1], ray.org[2]);
        else
            printf("ray %d from (%g, %g, %g): triangle %u at t = %g, u = %g, v = %g\n", i,
                   ray.org[0], ray.org[1], ray.org[2], (unsigned)hit.prim, hit.t, hit.u, hit.v);
    }
    brt_bvh_free(bvh);
    if (argc > 1) brt_mesh_free(&mesh);
    return 0;
}
