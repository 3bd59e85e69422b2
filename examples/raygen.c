/*
** examples/raygen.c -- test rays for a mesh, deterministic from --seed.
**
**   build/raygen MESH OUT.rays --kind camera|random|bounce [--count N] [--seed S]
**
** camera  a pinhole camera (45 degree field of view) outside the mesh,
**         looking at the centre of its bounding box from +z and a little
**         above (+y), just far enough back that the whole box is in view;
**         one ray per pixel of a near-square grid, jittered inside the
**         pixel.  Coherent rays, like primary rays of a renderer.
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
#include "common.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *const prog = "raygen";

#define PI 3.14159265358979323846
#define FOV_DEGREES 45.0
/* A bounce ray gives up after this many camera rays that miss the mesh;
** only a mesh that is invisible from the camera gets near it. */
#define MAX_CAMERA_ATTEMPTS 100000

enum ray_kind { KIND_CAMERA, KIND_RANDOM, KIND_BOUNCE };

typedef struct camera {
    double eye[3];
    double forward[3], right[3], up[3];   /* right and up scaled to the view */
    uint32_t width, height;               /* the pixel grid */
} camera;

static void usage(void)
{
    printf("usage: build/raygen MESH OUT.rays --kind camera|random|bounce [--count N] [--seed S]\n"
           "Writes N test rays for MESH (OBJ or PLY) as 32-byte records.\n"
           "\n"
           "  --kind camera   pinhole camera, fov 45 degrees, looking at the bounding-box\n"
           "                  centre from +z and a little above, jittered pixel grid\n"
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

/* ---- small vector helpers (double, so rays round once, at the end) ---- */

static double dot3(const double a[3], const double b[3])
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static void cross3(const double a[3], const double b[3], double out[3])
{
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

static void normalize3(double v[3])
{
    double len = sqrt(dot3(v, v));
    if (len > 0) { v[0] /= len; v[1] /= len; v[2] /= len; }
}

static void set_ray(brt_ray *ray, const double org[3], const double dir[3])
{
    double d[3];
    int k;
    memcpy(d, dir, sizeof d);
    normalize3(d);
    for (k = 0; k < 3; k++) {
        ray->org[k] = (float)org[k];
        ray->dir[k] = (float)d[k];
    }
    ray->tnear = 0.0f;
    ray->tfar = INFINITY;
}

/* ---- camera rays ---- */

static void camera_init(camera *cam, const float bmin[3], const float bmax[3], size_t count)
{
    double centre[3], back[3] = {0.0, 0.35, 1.0}, world_up[3] = {0, 1, 0};
    double half = tan(FOV_DEGREES * PI / 360.0), aspect, tan_x, tan_y, distance = 0;
    int k, corner;
    for (k = 0; k < 3; k++) centre[k] = 0.5 * ((double)bmin[k] + (double)bmax[k]);
    normalize3(back);
    for (k = 0; k < 3; k++) cam->forward[k] = -back[k];
    cross3(cam->forward, world_up, cam->right);
    normalize3(cam->right);
    cross3(cam->right, cam->forward, cam->up);
    cam->width = (uint32_t)ceil(sqrt((double)count));
    cam->height = (uint32_t)((count + cam->width - 1) / cam->width);
    /* Square pixels: the longer side of the grid spans the 45 degrees. */
    aspect = (double)cam->height / (double)cam->width;
    tan_x = aspect > 1 ? half / aspect : half;
    tan_y = aspect > 1 ? half : half * aspect;
    /* Back off until all eight box corners are in view (with a 5 % margin):
    ** a corner at offset o from the centre needs distance >= o.back +
    ** |o.right| / tan_x and >= o.back + |o.up| / tan_y.  The eye then lies
    ** beyond every corner along back, so outside the box. */
    for (corner = 0; corner < 8; corner++) {
        double o[3];
        for (k = 0; k < 3; k++)
            o[k] = ((corner >> k) & 1 ? (double)bmax[k] : (double)bmin[k]) - centre[k];
        distance = fmax(distance, dot3(o, back) + fmax(fabs(dot3(o, cam->right)) / tan_x,
                                                       fabs(dot3(o, cam->up)) / tan_y));
    }
    distance = distance > 0 ? 1.05 * distance : 1.0;   /* a one-point "box" */
    for (k = 0; k < 3; k++) {
        cam->eye[k] = centre[k] + distance * back[k];
        cam->right[k] *= tan_x;
        cam->up[k] *= tan_y;
    }
}

/* The ray through image point (sx, sy) in [0,1)^2, top left first. */
static void camera_ray(const camera *cam, double sx, double sy, brt_ray *ray)
{
    double dir[3], x = 2.0 * sx - 1.0, y = 1.0 - 2.0 * sy;
    int k;
    for (k = 0; k < 3; k++) dir[k] = cam->forward[k] + x * cam->right[k] + y * cam->up[k];
    set_ray(ray, cam->eye, dir);
}

static void camera_pixel_ray(const camera *cam, size_t i, uint64_t *rng, brt_ray *ray)
{
    double sx = ((double)(i % cam->width) + brt_random_float(rng)) / cam->width;
    double sy = ((double)(i / cam->width) + brt_random_float(rng)) / cam->height;
    camera_ray(cam, sx, sy, ray);
}

static void make_camera_rays(const camera *cam, brt_ray *rays, size_t count, uint64_t *rng)
{
    size_t i;
    for (i = 0; i < count; i++) camera_pixel_ray(cam, i, rng, &rays[i]);
}

/* ---- random rays ---- */

static void random_direction(uint64_t *rng, double dir[3])
{
    /* Archimedes: z uniform in [-1,1] and a uniform angle give a uniform
    ** point on the sphere. */
    double z = 1.0 - 2.0 * brt_random_float(rng);
    double phi = 2.0 * PI * brt_random_float(rng), r = sqrt(fmax(0.0, 1.0 - z * z));
    dir[0] = r * cos(phi);
    dir[1] = r * sin(phi);
    dir[2] = z;
}

static void make_random_rays(const float bmin[3], const float bmax[3], brt_ray *rays,
                             size_t count, uint64_t *rng)
{
    double lo[3], size[3], margin = 0;
    size_t i;
    int k;
    for (k = 0; k < 3; k++) margin = fmax(margin, 0.05 * ((double)bmax[k] - (double)bmin[k]));
    /* Growing by the longest side keeps a flat mesh's box from being flat. */
    for (k = 0; k < 3; k++) {
        lo[k] = (double)bmin[k] - margin;
        size[k] = (double)bmax[k] - (double)bmin[k] + 2.0 * margin;
    }
    for (i = 0; i < count; i++) {
        double org[3], dir[3];
        for (k = 0; k < 3; k++) org[k] = lo[k] + size[k] * brt_random_float(rng);
        random_direction(rng, dir);
        set_ray(&rays[i], org, dir);
    }
}

/* ---- bounce rays ---- */

/* A camera ray for bounce ray i that hits the mesh: pixel i first, then
** random image points until one hits.  Returns 0 when none does. */
static int camera_hit(const camera *cam, const brt_bvh *bvh, size_t i, uint64_t *rng,
                      brt_ray *ray, brt_hit *hit)
{
    int attempt;
    camera_pixel_ray(cam, i, rng, ray);
    for (attempt = 0; attempt < MAX_CAMERA_ATTEMPTS; attempt++) {
        brt_hit_clear(hit);
        brt_bvh_intersect(bvh, ray, hit);
        if (hit->prim != BRT_NO_PRIM) return 1;
        camera_ray(cam, brt_random_float(rng), brt_random_float(rng), ray);
    }
    return 0;
}

/* Orthonormal basis (t, b) around the unit normal n (Duff et al. 2017). */
static void tangent_frame(const double n[3], double t[3], double b[3])
{
    double s = n[2] >= 0 ? 1.0 : -1.0, a = -1.0 / (s + n[2]), c = n[0] * n[1] * a;
    t[0] = 1.0 + s * n[0] * n[0] * a; t[1] = s * c;           t[2] = -s * n[0];
    b[0] = c;                         b[1] = s + n[1] * n[1] * a; b[2] = -n[1];
}

static void bounce_ray(const brt_mesh *mesh, double diagonal, const brt_ray *in,
                       const brt_hit *hit, uint64_t *rng, brt_ray *out)
{
    const uint32_t *tri = mesh->indices + 3 * (size_t)hit->prim;
    double v[3][3], e1[3], e2[3], n[3], t[3], b[3], p[3], dir[3], scale = 0;
    double r = sqrt(brt_random_float(rng)), phi = 2.0 * PI * brt_random_float(rng);
    double x = r * cos(phi), y = r * sin(phi), z = sqrt(fmax(0.0, 1.0 - r * r));
    int j, k;
    for (j = 0; j < 3; j++)
        for (k = 0; k < 3; k++) v[j][k] = mesh->positions[3 * (size_t)tri[j] + k];
    for (k = 0; k < 3; k++) {
        e1[k] = v[1][k] - v[0][k];
        e2[k] = v[2][k] - v[0][k];
        p[k] = (1.0 - hit->u - hit->v) * v[0][k] + hit->u * v[1][k] + hit->v * v[2][k];
        scale = fmax(scale, fabs(p[k]));
    }
    cross3(e1, e2, n);
    normalize3(n);
    if (n[0] * in->dir[0] + n[1] * in->dir[1] + n[2] * in->dir[2] > 0)
        for (k = 0; k < 3; k++) n[k] = -n[k];
    tangent_frame(n, t, b);
    /* The offset is relative to the mesh size and to the coordinates'
    ** magnitude, so the nudged origin clears the surface by many float ulps
    ** at any scale and any distance from the origin. */
    scale = 1e-5 * (scale + diagonal);
    for (k = 0; k < 3; k++) {
        p[k] += scale * n[k];
        dir[k] = x * t[k] + y * b[k] + z * n[k];
    }
    set_ray(out, p, dir);
}

static void make_bounce_rays(const char *mesh_path, const brt_mesh *mesh, const camera *cam,
                             brt_ray *rays, size_t count, uint64_t *rng)
{
    brt_bvh *bvh;
    float bmin[3], bmax[3];
    double diagonal = 0;
    size_t i;
    int k;
    brt_mesh_bounds(mesh, bmin, bmax);
    for (k = 0; k < 3; k++)
        diagonal += ((double)bmax[k] - bmin[k]) * ((double)bmax[k] - bmin[k]);
    diagonal = sqrt(diagonal);
    ex_progress("building BVH", 0, 1);
    ex_check(prog, brt_bvh_build(mesh->positions, mesh->indices, mesh->triangle_count,
                                 NULL, &bvh), NULL);
    for (i = 0; i < count; i++) {
        brt_ray in;
        brt_hit hit;
        if ((i & 0xFFFF) == 0) ex_progress("bounce rays", i, count);
        if (!camera_hit(cam, bvh, i, rng, &in, &hit))
            ex_die(prog, "%s: no camera ray hit the mesh in %d attempts: nothing to bounce from",
                   mesh_path, MAX_CAMERA_ATTEMPTS);
        bounce_ray(mesh, diagonal, &in, &hit, rng, &rays[i]);
    }
    ex_progress("bounce rays", count, count);
    ex_progress_end();
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
    enum ray_kind kind;
    brt_mesh mesh;
    brt_error err;
    brt_ray *rays;
    float bmin[3], bmax[3];
    camera cam;
    int i;

    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (strcmp(a, "--kind") == 0) kind_text = ex_option_value(prog, argc, argv, &i);
        else if (strcmp(a, "--count") == 0)
            count = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 1, UINT32_MAX);
        else if (strcmp(a, "--seed") == 0)
            seed = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 0, UINT64_MAX);
        else if (a[0] == '-' && a[1] != 0) ex_die(prog, "unknown option '%s' (see --help)", a);
        else if (!mesh_path) mesh_path = a;
        else if (!out_path) out_path = a;
        else ex_die(prog, "unexpected argument '%s' (see --help)", a);
    }
    if (!out_path) ex_die(prog, "expected MESH OUT.rays (see --help)");
    if (!kind_text) ex_die(prog, "--kind camera|random|bounce is required (see --help)");
    kind = parse_kind(kind_text);

    /* The loader refuses a mesh without triangles, so the box is not empty. */
    ex_check(prog, brt_mesh_load(mesh_path, &mesh, &err), &err);
    brt_mesh_bounds(&mesh, bmin, bmax);
    rays = malloc((size_t)count * sizeof *rays);
    if (!rays) ex_die(prog, "out of memory for %llu rays", (unsigned long long)count);

    rng = seed;
    camera_init(&cam, bmin, bmax, (size_t)count);
    if (kind == KIND_CAMERA) make_camera_rays(&cam, rays, (size_t)count, &rng);
    else if (kind == KIND_RANDOM) make_random_rays(bmin, bmax, rays, (size_t)count, &rng);
    else make_bounce_rays(mesh_path, &mesh, &cam, rays, (size_t)count, &rng);

    ex_check(prog, brt_rays_write(out_path, rays, (size_t)count, &err), &err);
    free(rays);
    brt_mesh_free(&mesh);
    return 0;
}
