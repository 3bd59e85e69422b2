/*
** tests/test_sampling.c -- the ray samplers of examples/lib/rays.c against
** closed-form moments.
**
** raygen and render draw directions from three distributions, and every
** image and ray file depends on them being what their comments say.  A
** sampler that is slightly off still gives plausible rays, so each test
** compares sample means with their exact values, within 5 standard errors
** of the sample (1 in 1.7 million to fail by chance; the seed is fixed):
**   uniform in a cone of half-angle acos(c) about the axis:
**     cos theta is uniform in [c, 1]: E = (1 + c) / 2, Var = (1 - c)^2 / 12
**   cosine-weighted about the normal (Malley): E[cos] = 2/3, E[cos^2] = 1/2
**   the sphere (random rays): E[d] = 0, E[d_k^2] = 1/3 for every axis
**   origins uniform in the box grown by 5 % of its longest side: the means
**     are the centre, and the extremes reach the grown box's faces
**   camera ray i through pixel (i mod width, i div width), jittered
**     uniformly in it: the offset in the pixel has mean 1/2 and variance
**     1/12 on each axis
*/
#include "test.h"
#include "util.h"
#include "../examples/lib/rays.h"

#include <math.h>
#include <stdlib.h>

enum { SAMPLES = 200000 };

/* Running mean and variance (Welford), for the standard error. */
typedef struct moments {
    double n, mean, m2;
} moments;

static void moments_add(moments *m, double x)
{
    double d = x - m->mean;
    m->n += 1.0;
    m->mean += d / m->n;
    m->m2 += d * (x - m->mean);
}

/* Whether the sample mean is within 5 standard errors of want; says so. */
static int mean_near(const moments *m, double want, const char *what)
{
    double se = sqrt(m->m2 / (m->n - 1.0) / m->n);
    int ok = fabs(m->mean - want) <= 5.0 * se + 1e-12;
    EXPECT(ok, "%s: mean %.6f, exact %.6f (standard error %.2g)", what, m->mean, want, se);
    return ok;
}

static double cosine_to(const brt_ray *r, const double axis[3])
{
    double len = sqrt((double)r->dir[0] * r->dir[0] + (double)r->dir[1] * r->dir[1] +
                      (double)r->dir[2] * r->dir[2]);
    return ((double)r->dir[0] * axis[0] + (double)r->dir[1] * axis[1] + (double)r->dir[2] * axis[2]) / len;
}

static void test_cone(void)
{
    static const double axes[2][3] = {{0.48, 0.62, 0.62}, {0, 0, -1}};
    static const double cos_max[2] = {0.99863, 0.5};   /* a sun of 3 degrees, a wide cone */
    uint64_t rng = test_seed();
    int a, c;
    long i;
    for (a = 0; a < 2; a++)
        for (c = 0; c < 2; c++) {
            double axis[3], len = sqrt(axes[a][0] * axes[a][0] + axes[a][1] * axes[a][1] + axes[a][2] * axes[a][2]);
            static const double origin[3] = {1, 2, 3};
            moments z = {0, 0, 0};
            int k;
            for (k = 0; k < 3; k++) axis[k] = axes[a][k] / len;
            for (i = 0; i < SAMPLES; i++) {
                brt_ray r;
                double u1 = brt_random_float(&rng), u2 = brt_random_float(&rng);
                ex_cone_ray(origin, axis, cos_max[c], u1, u2, &r);
                moments_add(&z, cosine_to(&r, axis));
            }
            mean_near(&z, 0.5 * (1.0 + cos_max[c]), "cone: cos theta");
        }
}

static void test_lambert(void)
{
    static const double normal[3] = {0.3, -0.4, 0.866};
    static const double point[3] = {10, -5, 2};
    static const float incoming[3] = {0, 0, -1};
    double n[3], len = sqrt(normal[0] * normal[0] + normal[1] * normal[1] + normal[2] * normal[2]);
    uint64_t rng = test_seed() + 1;
    moments c1 = {0, 0, 0}, c2 = {0, 0, 0};
    long i;
    int k;
    for (k = 0; k < 3; k++) n[k] = normal[k] / len;
    for (i = 0; i < SAMPLES; i++) {
        brt_ray r;
        double u1 = brt_random_float(&rng), u2 = brt_random_float(&rng), c;
        CHECK(ex_lambert_bounce(point, normal, incoming, 1.0, u1, u2, &r), "no bounce");
        c = cosine_to(&r, n);
        CHECK(c >= 0, "a bounce below the surface (cos %g)", c);
        moments_add(&c1, c);
        moments_add(&c2, c * c);
    }
    mean_near(&c1, 2.0 / 3.0, "lambert: cos theta");
    mean_near(&c2, 0.5, "lambert: cos^2 theta");
}

static void test_random_rays(void)
{
    static const float lo[3] = {-1, 0, 2}, hi[3] = {3, 1, 2.5f};
    const double margin = 0.05 * 4.0;   /* the longest side is x's */
    brt_ray *rays = malloc(SAMPLES * sizeof *rays);
    uint64_t rng = test_seed() + 2;
    moments dir[3] = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}}, sq[3] = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}};
    moments org[3] = {{0, 0, 0}, {0, 0, 0}, {0, 0, 0}};
    double omin[3] = {INFINITY, INFINITY, INFINITY}, omax[3] = {-INFINITY, -INFINITY, -INFINITY};
    long i;
    int k;
    CHECK(rays, "out of memory");
    ex_rays_random(lo, hi, rays, SAMPLES, &rng);
    for (i = 0; i < SAMPLES; i++)
        for (k = 0; k < 3; k++) {
            moments_add(&dir[k], rays[i].dir[k]);
            moments_add(&sq[k], (double)rays[i].dir[k] * rays[i].dir[k]);
            moments_add(&org[k], rays[i].org[k]);
            omin[k] = fmin(omin[k], rays[i].org[k]);
            omax[k] = fmax(omax[k], rays[i].org[k]);
        }
    for (k = 0; k < 3; k++) {
        double grown = (double)hi[k] - lo[k] + 2 * margin;
        mean_near(&dir[k], 0.0, "random: direction component");
        mean_near(&sq[k], 1.0 / 3.0, "random: direction component squared");
        mean_near(&org[k], 0.5 * ((double)lo[k] + hi[k]), "random: origin");
        /* The extremes of 200 000 uniform draws lie within 1e-4 of the
        ** grown box's faces (the chance of a gap wider is e^-20). */
        EXPECT(omin[k] >= lo[k] - margin - 1e-5 && omin[k] <= lo[k] - margin + 1e-4 * grown &&
               omax[k] <= hi[k] + margin + 1e-5 && omax[k] >= hi[k] + margin - 1e-4 * grown,
               "random: origins on axis %d span [%g, %g], the grown box [%g, %g]", k, omin[k], omax[k],
               lo[k] - margin, hi[k] + margin);
    }
    free(rays);
}

/* Where ray r meets the image plane of cam, in pixels from the top left. */
static void pixel_of(const ex_camera *cam, const brt_ray *r, double *px, double *py)
{
    double d[3] = {r->dir[0], r->dir[1], r->dir[2]};
    double f = ex_dot3(d, cam->forward);
    double x = ex_dot3(d, cam->right) / f / ex_dot3(cam->right, cam->right);
    double y = ex_dot3(d, cam->up) / f / ex_dot3(cam->up, cam->up);
    *px = 0.5 * (x + 1.0) * cam->width;
    *py = 0.5 * (1.0 - y) * cam->height;
}

static void test_camera_jitter(void)
{
    static const float lo[3] = {-2, -1, -3}, hi[3] = {4, 2, 1};
    enum { W = 160, H = 90, COUNT = W * H };
    brt_ray *rays = malloc(COUNT * sizeof *rays);
    ex_camera cam;
    uint64_t rng = test_seed() + 3;
    moments fx = {0, 0, 0}, fy = {0, 0, 0};
    long i, misplaced = 0;
    CHECK(rays, "out of memory");
    ex_camera_fit(&cam, lo, hi, W, H);
    ex_rays_camera(&cam, rays, COUNT, &rng);
    for (i = 0; i < COUNT; i++) {
        double px, py, want_x = (double)(i % W), want_y = (double)(i / W);   /* rows past H lie below the image, as documented */
        pixel_of(&cam, &rays[i], &px, &py);
        /* The float direction moves the point by far less than 1e-3 pixel. */
        misplaced += px < want_x - 1e-3 || px > want_x + 1 + 1e-3 || py < want_y - 1e-3 || py > want_y + 1 + 1e-3;
        moments_add(&fx, px - want_x);
        moments_add(&fy, py - want_y);
    }
    EXPECT(misplaced == 0, "camera: %ld of %d rays outside their pixel", misplaced, (int)COUNT);
    mean_near(&fx, 0.5, "camera: offset in the pixel, x");
    mean_near(&fy, 0.5, "camera: offset in the pixel, y");
    /* A uniform offset's variance is 1/12; its estimate's standard error
    ** here is sqrt((1/80 - 1/144) / COUNT), under 7e-4. */
    EXPECT(fabs(fx.m2 / (fx.n - 1) - 1.0 / 12) < 3.5e-3 && fabs(fy.m2 / (fy.n - 1) - 1.0 / 12) < 3.5e-3,
           "camera: offsets in the pixel vary by %g and %g, uniform ones by 1/12", fx.m2 / (fx.n - 1),
           fy.m2 / (fy.n - 1));
    free(rays);
}

void suite_sampling(void)
{
    test_run("sampling: cone directions uniform in solid angle (the sun)", test_cone);
    test_run("sampling: Lambert bounces cosine-weighted", test_lambert);
    test_run("sampling: random rays uniform on the sphere, origins in the grown box", test_random_rays);
    test_run("sampling: camera rays jittered uniformly in their pixels", test_camera_jitter);
}
