/*
** examples/lib/rays.h -- rays for the example programs: a pinhole camera,
** uniformly random rays and cosine-weighted bounce rays.  Every ray has a
** unit direction, tnear = 0 and tfar = +inf; everything is deterministic
** from the caller's SplitMix64 state (brt_random_u64).
*/
#ifndef BRT_EXAMPLES_RAYS_H
#define BRT_EXAMPLES_RAYS_H

#include "common.h"

#define EX_CAMERA_FOV 45.0   /* degrees across the longer side of the image */
/* A bounce ray gives up after this many camera rays that miss the mesh;
** only a mesh that is invisible from the camera gets near it. */
#define EX_MAX_CAMERA_ATTEMPTS 100000

/* A pinhole camera over a grid of width x height square pixels. */
typedef struct ex_camera {
    double eye[3];
    double forward[3], right[3], up[3];   /* right and up scaled to the view */
    uint32_t width, height;
} ex_camera;

/* The default view of a box: its centre seen from +z and a little above
** (+y), just far enough back that all eight corners are in view. */
void ex_camera_fit(ex_camera *cam, const float bmin[3], const float bmax[3],
                   uint32_t width, uint32_t height);
/* A camera at eye looking at target, y up. */
void ex_camera_look(ex_camera *cam, const float eye[3], const float target[3],
                    double fov_degrees, uint32_t width, uint32_t height);
/* The ray through image point (sx, sy) in [0,1)^2, top left first. */
void ex_camera_ray(const ex_camera *cam, double sx, double sy, brt_ray *ray);

/* Ray i through pixel (i mod width, i div width), jittered in the pixel. */
void ex_rays_camera(const ex_camera *cam, brt_ray *rays, size_t count, uint64_t *rng);
/* Origins uniform in the box grown on every side by 5 % of its longest
** side, directions uniform on the sphere. */
void ex_rays_random(const float bmin[3], const float bmax[3], brt_ray *rays, size_t count,
                    uint64_t *rng);
/* Length of the diagonal of a box, and of the mesh's bounding box. */
double ex_box_diagonal(const float bmin[3], const float bmax[3]);
double ex_mesh_diagonal(const brt_mesh *mesh);
/* A Lambert bounce: from point nudged off the surface along the normal
** (any length, either side) turned to face the incoming direction, a
** cosine-weighted direction about it from the uniform numbers (u1, u2)
** (Malley's method).  The nudge is 1e-5 of the scene diagonal plus the
** point's largest |coordinate|.  Returns 0 for a zero normal. */
int ex_lambert_bounce(const double point[3], const double normal[3], const float incoming[3],
                      double diagonal, double u1, double u2, brt_ray *out);
/* The two halves of it: the unit normal n turned to face the incoming
** direction and the point p nudged along it (0 for a zero normal); and a
** ray from origin in a direction uniform in the cone of directions within
** acos(cos_max) of the unit axis, from (u1, u2) (a sun's disc). */
int ex_surface_point(const double point[3], const double normal[3], const float incoming[3],
                     double diagonal, double n[3], double p[3]);
void ex_cone_ray(const double origin[3], const double axis[3], double cos_max, double u1,
                 double u2, brt_ray *out);
/* ex_lambert_bounce at the hit of ray in, with the triangle's normal and
** two numbers drawn from rng. */
void ex_bounce_ray(const brt_mesh *mesh, double diagonal, const brt_ray *in,
                   const brt_hit *hit, uint64_t *rng, brt_ray *out);
/* count bounce rays from camera rays that hit (pixel i first, then random
** image points); 0 when no camera ray hits the mesh at all.  The same for
** a world (an instanced scene): the hit point from t, the normal the
** world's. */
int ex_rays_bounce_world(const brt_world *world, const ex_camera *cam, brt_ray *rays,
                         size_t count, uint64_t *rng);
int ex_rays_bounce(const brt_mesh *mesh, const brt_bvh *bvh, const ex_camera *cam,
                   brt_ray *rays, size_t count, uint64_t *rng);

#endif
