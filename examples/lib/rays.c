/*
** examples/lib/rays.c -- the rays of the example programs (rays.h): a pinhole
** camera, uniformly random rays, and bounce rays that leave a surface in a
** cosine-weighted direction.  Shared by raygen, the benchmarks, voxelize
** and the renderer, so that they all trace the same kinds of rays.
**
** Geometry is done in double so each ray rounds once, at the end.  The
** random numbers come from brt_random_u64/brt_random_float (SplitMix64):
** the same inputs and seed give the same bytes run after run (across
** machines too, as long as their libm rounds sin, cos and tan alike).
*/
#include "rays.h"

#include <math.h>
#include <string.h>

#define PI 3.14159265358979323846

/* ---- small vector helpers: ex_dot3, ex_cross3, ex_normalize3 (common.c) */

static void set_ray(brt_ray *ray, const double org[3], const double dir[3])
{
    double d[3];
    int k;
    memcpy(d, dir, sizeof d);
    ex_normalize3(d);
    for (k = 0; k < 3; k++) {
        ray->org[k] = (float)org[k];
        ray->dir[k] = (float)d[k];
    }
    ray->tnear = 0.0f;
    ray->tfar = INFINITY;
}

/* ---- camera rays ---- */

/* The frame of a camera looking along forward (unit), y up. */
static void camera_frame(ex_camera *cam, const double forward[3], uint32_t width, uint32_t height)
{
    double world_up[3] = {0, 1, 0};
    memcpy(cam->forward, forward, sizeof cam->forward);
    ex_cross3(cam->forward, world_up, cam->right);
    if (ex_dot3(cam->right, cam->right) == 0) cam->right[0] = 1;   /* looking straight up or down */
    ex_normalize3(cam->right);
    ex_cross3(cam->right, cam->forward, cam->up);
    cam->width = width;
    cam->height = height;
}

/* Half-angle tangents of a view whose longer side spans fov_degrees. */
static void view_tangents(const ex_camera *cam, double fov_degrees, double *tan_x, double *tan_y)
{
    double half = tan(fov_degrees * PI / 360.0);
    double aspect = (double)cam->height / (double)cam->width;   /* square pixels */
    *tan_x = aspect > 1 ? half / aspect : half;
    *tan_y = aspect > 1 ? half : half * aspect;
}

void ex_camera_look(ex_camera *cam, const float eye[3], const float target[3],
                    double fov_degrees, uint32_t width, uint32_t height)
{
    double forward[3], tan_x, tan_y;
    int k;
    for (k = 0; k < 3; k++) forward[k] = (double)target[k] - (double)eye[k];
    ex_normalize3(forward);
    camera_frame(cam, forward, width, height);
    view_tangents(cam, fov_degrees, &tan_x, &tan_y);
    for (k = 0; k < 3; k++) {
        cam->eye[k] = eye[k];
        cam->right[k] *= tan_x;
        cam->up[k] *= tan_y;
    }
}

void ex_camera_fit(ex_camera *cam, const float bmin[3], const float bmax[3], uint32_t width,
                   uint32_t height)
{
    double centre[3], back[3] = {0.0, 0.35, 1.0}, forward[3], tan_x, tan_y, distance = 0;
    int k, corner;
    for (k = 0; k < 3; k++) centre[k] = 0.5 * ((double)bmin[k] + (double)bmax[k]);
    ex_normalize3(back);
    for (k = 0; k < 3; k++) forward[k] = -back[k];
    camera_frame(cam, forward, width, height);
    view_tangents(cam, EX_CAMERA_FOV, &tan_x, &tan_y);
    /* Back off until all eight box corners are in view (with a 5 % margin):
    ** a corner at offset o from the centre needs distance >= o.back +
    ** |o.right| / tan_x and >= o.back + |o.up| / tan_y.  The eye then lies
    ** beyond every corner along back, so outside the box. */
    for (corner = 0; corner < 8; corner++) {
        double o[3];
        for (k = 0; k < 3; k++)
            o[k] = ((corner >> k) & 1 ? (double)bmax[k] : (double)bmin[k]) - centre[k];
        distance = fmax(distance, ex_dot3(o, back) + fmax(fabs(ex_dot3(o, cam->right)) / tan_x,
                                                       fabs(ex_dot3(o, cam->up)) / tan_y));
    }
    distance = distance > 0 ? 1.05 * distance : 1.0;   /* a one-point "box" */
    for (k = 0; k < 3; k++) {
        cam->eye[k] = centre[k] + distance * back[k];
        cam->right[k] *= tan_x;
        cam->up[k] *= tan_y;
    }
}

/* The ray through image point (sx, sy) in [0,1)^2, top left first. */
void ex_camera_ray(const ex_camera *cam, double sx, double sy, brt_ray *ray)
{
    double dir[3], x = 2.0 * sx - 1.0, y = 1.0 - 2.0 * sy;
    int k;
    for (k = 0; k < 3; k++) dir[k] = cam->forward[k] + x * cam->right[k] + y * cam->up[k];
    set_ray(ray, cam->eye, dir);
}

static void camera_pixel_ray(const ex_camera *cam, size_t i, uint64_t *rng, brt_ray *ray)
{
    double sx = ((double)(i % cam->width) + brt_random_float(rng)) / cam->width;
    double sy = ((double)(i / cam->width) + brt_random_float(rng)) / cam->height;
    ex_camera_ray(cam, sx, sy, ray);
}

void ex_rays_camera(const ex_camera *cam, brt_ray *rays, size_t count, uint64_t *rng)
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

void ex_rays_random(const float bmin[3], const float bmax[3], brt_ray *rays, size_t count,
                    uint64_t *rng)
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
/* The closest hit of a mesh's BVH or of a world (with its normal). */
typedef struct hit_scene {
    const brt_bvh *bvh;
    const brt_world *world;
} hit_scene;

static void scene_intersect(const hit_scene *sc, const brt_ray *ray, brt_hit *hit, float normal[3])
{
    brt_hit_clear(hit);
    if (sc->world) brt_world_intersect(sc->world, ray, hit, normal);
    else brt_bvh_intersect(sc->bvh, ray, hit);
}

static int camera_hit(const ex_camera *cam, const hit_scene *sc, size_t i, uint64_t *rng,
                      brt_ray *ray, brt_hit *hit, float normal[3])
{
    int attempt;
    camera_pixel_ray(cam, i, rng, ray);
    for (attempt = 0; attempt < EX_MAX_CAMERA_ATTEMPTS; attempt++) {
        scene_intersect(sc, ray, hit, normal);
        if (hit->prim != BRT_NO_PRIM) return 1;
        ex_camera_ray(cam, brt_random_float(rng), brt_random_float(rng), ray);
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

int ex_surface_point(const double point[3], const double normal[3], const float incoming[3],
                     double diagonal, double n[3], double p[3])
{
    double len = sqrt(ex_dot3(normal, normal)), scale = 0;
    int k;
    if (!(len > 0)) return 0;
    if (normal[0] * incoming[0] + normal[1] * incoming[1] + normal[2] * incoming[2] > 0) len = -len;
    for (k = 0; k < 3; k++) {
        n[k] = normal[k] / len;
        scale = fmax(scale, fabs(point[k]));
    }
    /* The offset is relative to the scene size and to the coordinates'
    ** magnitude, so the nudged origin clears the surface by many float ulps
    ** at any scale and any distance from the origin. */
    scale = 1e-5 * (scale + diagonal);
    for (k = 0; k < 3; k++) p[k] = point[k] + scale * n[k];
    return 1;
}

int ex_lambert_bounce(const double point[3], const double normal[3], const float incoming[3],
                      double diagonal, double u1, double u2, brt_ray *out)
{
    double n[3], t[3], b[3], p[3], dir[3];
    double r = sqrt(u1), phi = 2.0 * PI * u2;
    double x = r * cos(phi), y = r * sin(phi), z = sqrt(fmax(0.0, 1.0 - u1));
    int k;
    if (!ex_surface_point(point, normal, incoming, diagonal, n, p)) return 0;
    tangent_frame(n, t, b);
    for (k = 0; k < 3; k++) dir[k] = x * t[k] + y * b[k] + z * n[k];
    set_ray(out, p, dir);
    return 1;
}

void ex_cone_ray(const double origin[3], const double axis[3], double cos_max, double u1,
                 double u2, brt_ray *out)
{
    double t[3], b[3], dir[3];
    double z = 1.0 - u1 * (1.0 - cos_max), r = sqrt(fmax(0.0, 1.0 - z * z)), phi = 2.0 * PI * u2;
    int k;
    tangent_frame(axis, t, b);
    for (k = 0; k < 3; k++) dir[k] = r * cos(phi) * t[k] + r * sin(phi) * b[k] + z * axis[k];
    set_ray(out, origin, dir);
}

void ex_bounce_ray(const brt_mesh *mesh, double diagonal, const brt_ray *in,
                   const brt_hit *hit, uint64_t *rng, brt_ray *out)
{
    const uint32_t *tri = mesh->indices + 3 * (size_t)hit->prim;
    double v[3][3], e1[3], e2[3], n[3], p[3], u1 = brt_random_float(rng), u2 = brt_random_float(rng);
    int j, k;
    for (j = 0; j < 3; j++)
        for (k = 0; k < 3; k++) v[j][k] = mesh->positions[3 * (size_t)tri[j] + k];
    for (k = 0; k < 3; k++) {
        e1[k] = v[1][k] - v[0][k];
        e2[k] = v[2][k] - v[0][k];
        p[k] = (1.0 - hit->u - hit->v) * v[0][k] + hit->u * v[1][k] + hit->v * v[2][k];
    }
    ex_cross3(e1, e2, n);
    ex_lambert_bounce(p, n, in->dir, diagonal, u1, u2, out);
}

double ex_box_diagonal(const float bmin[3], const float bmax[3])
{
    double d = 0;
    int k;
    for (k = 0; k < 3; k++) d += ((double)bmax[k] - bmin[k]) * ((double)bmax[k] - bmin[k]);
    return sqrt(d);
}

double ex_mesh_diagonal(const brt_mesh *mesh)
{
    float bmin[3], bmax[3];
    brt_mesh_bounds(mesh, bmin, bmax);
    return ex_box_diagonal(bmin, bmax);
}

/* count bounce rays from camera hits: a mesh's (the hit point from the
** barycentrics, the triangle's normal) or a world's (the point from t,
** the world's normal). */
static int bounce_rays(const hit_scene *sc, const brt_mesh *mesh, double diagonal,
                       const ex_camera *cam, brt_ray *rays, size_t count, uint64_t *rng)
{
    size_t i;
    for (i = 0; i < count; i++) {
        brt_ray in;
        brt_hit hit;
        float normal[3];
        if ((i & 0xFFFF) == 0) ex_progress("bounce rays", i, count);
        if (!camera_hit(cam, sc, i, rng, &in, &hit, normal)) return 0;
        if (mesh) {
            ex_bounce_ray(mesh, diagonal, &in, &hit, rng, &rays[i]);
        } else {
            double p[3], n[3], u1 = brt_random_float(rng), u2 = brt_random_float(rng);
            int k;
            for (k = 0; k < 3; k++) {
                p[k] = (double)in.org[k] + (double)hit.t * in.dir[k];
                n[k] = normal[k];
            }
            ex_lambert_bounce(p, n, in.dir, diagonal, u1, u2, &rays[i]);
        }
    }
    ex_progress("bounce rays", count, count);
    ex_progress_end();
    return 1;
}

int ex_rays_bounce(const brt_mesh *mesh, const brt_bvh *bvh, const ex_camera *cam,
                   brt_ray *rays, size_t count, uint64_t *rng)
{
    hit_scene sc;
    sc.bvh = bvh;
    sc.world = NULL;
    return bounce_rays(&sc, mesh, ex_mesh_diagonal(mesh), cam, rays, count, rng);
}

int ex_rays_bounce_world(const brt_world *world, const ex_camera *cam, brt_ray *rays,
                         size_t count, uint64_t *rng)
{
    float bmin[3], bmax[3];
    hit_scene sc;
    sc.bvh = NULL;
    sc.world = world;
    brt_world_bounds(world, bmin, bmax);
    return bounce_rays(&sc, NULL, ex_box_diagonal(bmin, bmax), cam, rays, count, rng);
}
