/*
** examples/tools/raygen.c -- test rays for a mesh, deterministic from --seed.
**
**   build/raygen MESH OUT.rays --kind camera|random|bounce [--count N] [--seed S]
**
** camera  a pinhole camera (45 degree field of view) outside the mesh,
**         looking at the centre of its bounding box from +z and a little
**         above (+y), just far enough back that the whole box is in view;
**         one ray per pixel of a near-square grid, jittered inside the
**         pixel.  Coherent rays, like primary rays of a renderer.
**         A .pbrt file with a perspective Camera: that camera at its
**         Film's resolution (examples/lib/pbrt.h), one ray through each pixel
**         centre in raster order (row by row from the top, each row left
**         to right); --count, default every pixel, takes the first N.
** random  origins uniform in the bounding box grown on every side by 5 % of
**         its longest side, directions uniform on the sphere.  The
**         incoherent extreme.
** bounce  secondary rays: camera rays are traced with the BVH; from each
**         hit point, nudged off the surface along the geometric normal on
**         the side the camera ray came from, a cosine-weighted direction in
**         that hemisphere (Malley's method).  A camera ray that misses is
**         replaced by one through a random point of the image.
**
** All directions are normalised, tnear = 0 and tfar = +inf.  The random
** numbers come from brt_random_u64/brt_random_float (SplitMix64), so the
** same mesh, kind, count and seed give the same bytes run after run.  (Across
** machines too, as long as their libm rounds sin, cos and tan alike: C99
** does not promise correctly rounded transcendental functions.)
*/
#include "input.h"
#include "rays.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *const prog = "raygen";

enum ray_kind { KIND_CAMERA, KIND_RANDOM, KIND_BOUNCE };

static void usage(void)
{
    printf("usage: build/raygen MESH OUT.rays --kind camera|random|bounce [--count N] [--seed S]\n"
           "Writes N test rays for MESH (OBJ, PLY or a pbrt-v4 .pbrt scene) as 32-byte records.\n"
           "\n"
           "  --kind camera   pinhole camera, fov 45 degrees, looking at the bounding-box\n"
           "                  centre from +z and a little above, jittered pixel grid;\n"
           "                  a .pbrt file's camera: its Film's pixel centres in raster\n"
           "                  order (rows from the top, left to right), --count the first N\n"
           "  --kind random   origins uniform in the bounding box grown on every side by\n"
           "                  5 %% of its longest side, directions uniform on the sphere\n"
           "  --kind bounce   from camera-ray hit points, cosine-weighted directions\n"
           "                  about the geometric normal facing the camera\n"
           "  --count N       number of rays, N >= 1 (default 1000000)\n"
           "  --seed S        random seed (default 1); the same seed gives the same bytes\n"
           "  --help          this text\n"
           "\n"
           "Directions are normalised, tnear = 0, tfar = +inf.\n");
}

static void make_bounce_rays(const char *mesh_path, const brt_mesh *mesh, const ex_camera *cam,
                             brt_ray *rays, size_t count, uint64_t *rng)
{
    brt_bvh *bvh;
    ex_progress("building BVH", 0, 1);
    ex_check(prog, brt_bvh_build(mesh->positions, mesh->indices, mesh->triangle_count,
                                 NULL, &bvh), NULL);
    if (!ex_rays_bounce(mesh, bvh, cam, rays, count, rng))
        ex_die(prog, "%s: no camera ray hit the mesh in %d attempts: nothing to bounce from",
               mesh_path, EX_MAX_CAMERA_ATTEMPTS);
    brt_bvh_free(bvh);
}

static enum ray_kind parse_kind(const char *text)
{
    if (strcmp(text, "camera") == 0) return KIND_CAMERA;
    if (strcmp(text, "random") == 0) return KIND_RANDOM;
    if (strcmp(text, "bounce") == 0) return KIND_BOUNCE;
    ex_die(prog, "--kind: expected camera, random or bounce, got '%s'", text);
}

int main(int argc, char **argv)
{
    const char *mesh_path = NULL, *out_path = NULL, *kind_text = NULL;
    uint64_t count = 1000000, seed = 1, rng;
    int have_count = 0;
    enum ray_kind kind;
    brt_mesh mesh;
    brt_world *world = NULL;
    ex_input input;
    brt_error err;
    brt_ray *rays;
    float bmin[3], bmax[3];
    ex_camera cam;
    uint32_t width;
    int i;

    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (strcmp(a, "--kind") == 0) kind_text = ex_option_value(prog, argc, argv, &i);
        else if (strcmp(a, "--count") == 0)
            count = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 1, UINT32_MAX), have_count = 1;
        else if (strcmp(a, "--seed") == 0)
            seed = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 0, UINT64_MAX);
        else if (a[0] == '-' && a[1] != 0) ex_unknown_option(prog, a);
        else if (!mesh_path) mesh_path = a;
        else if (!out_path) out_path = a;
        else ex_die(prog, "unexpected argument '%s' (see --help)", a);
    }
    if (!out_path) ex_die(prog, "expected MESH OUT.rays (see --help)");
    if (!kind_text) ex_die(prog, "--kind camera|random|bounce is required (see --help)");
    kind = parse_kind(kind_text);
    ex_catch_interrupts();   /* polled before the write; a failed build reports it (ex_check) */

    /* The loader refuses a mesh without triangles, so the box is not empty;
    ** a pbrt scene is traced through its world (an empty one has no rays). */
    ex_input_open(prog, mesh_path, &input);
    memset(&mesh, 0, sizeof mesh);
    if (input.pbrt) {
        world = ex_input_world(prog, &input);
        brt_world_bounds(world, bmin, bmax);
        if (!(bmin[0] <= bmax[0])) ex_die(prog, "%s: no triangles", mesh_path);
    } else {
        ex_check(prog, brt_mesh_load(mesh_path, &mesh, &err), &err);
        brt_mesh_bounds(&mesh, bmin, bmax);
    }
    if (kind == KIND_CAMERA && input.pbrt) {   /* the file's camera, pixel centres */
        uint32_t w, h;
        ex_pbrt_film(input.pbrt, &w, &h);
        if (ex_pbrt_camera_frame(input.pbrt, w, h, cam.eye, cam.forward, cam.right, cam.up)) {
            uint64_t pixels = (uint64_t)w * h, p;
            if (!have_count) count = pixels;
            if (count > pixels || count > UINT32_MAX)
                ex_die(prog, "%s: --count %llu: the Film has %llu pixels", mesh_path,
                       (unsigned long long)count, (unsigned long long)pixels);
            cam.width = w;
            cam.height = h;
            if (!(rays = malloc((size_t)count * sizeof *rays)))
                ex_die(prog, "out of memory for %llu rays", (unsigned long long)count);
            for (p = 0; p < count; p++)
                ex_camera_ray(&cam, ((double)(p % w) + 0.5) / w, ((double)(p / w) + 0.5) / h, &rays[p]);
            if (ex_interrupted()) ex_die_interrupted(prog);
    ex_check(prog, brt_rays_write(out_path, rays, (size_t)count, &err), &err);
            free(rays);
            brt_world_free(world);
            ex_input_close(&input);
            return 0;
        }
    }
    rays = malloc((size_t)count * sizeof *rays);
    if (!rays) ex_die(prog, "out of memory for %llu rays", (unsigned long long)count);

    rng = seed;
    /* A near-square pixel grid with one ray per pixel. */
    width = (uint32_t)ceil(sqrt((double)count));
    ex_camera_fit(&cam, bmin, bmax, width, (uint32_t)((count + width - 1) / width));
    if (kind == KIND_CAMERA) ex_rays_camera(&cam, rays, (size_t)count, &rng);
    else if (kind == KIND_RANDOM) ex_rays_random(bmin, bmax, rays, (size_t)count, &rng);
    else if (world) {
        if (!ex_rays_bounce_world(world, &cam, rays, (size_t)count, &rng))
            ex_die(prog, "%s: no camera ray hit the scene in %d attempts: nothing to bounce from",
                   mesh_path, EX_MAX_CAMERA_ATTEMPTS);
    } else make_bounce_rays(mesh_path, &mesh, &cam, rays, (size_t)count, &rng);

    if (ex_interrupted()) ex_die_interrupted(prog);
    ex_check(prog, brt_rays_write(out_path, rays, (size_t)count, &err), &err);
    free(rays);
    brt_mesh_free(&mesh);
    brt_world_free(world);
    ex_input_close(&input);
    return 0;
}
