/*
** tests/test_pbrt_camera.c -- a pbrt-v4 file's camera and film as pbrt-v4
** defines them, against a model written here from pbrt-v4's definitions
** (src/pbrt/util/transform.cpp: LookAt, Rotate, Scale; cameras.cpp:
** PerspectiveCamera::Create's screen window, Perspective(fov), raster from
** screen with raster y pointing down), not from examples/.  The model
** projects world points to raster coordinates; the reader's camera frame
** (ex_pbrt_camera_frame, what render and raygen use) must send the ray
** through that raster point straight at the world point, and render must
** light the pixel the model names.  Also the film's size, raygen's pixel
** centres, and the reader's nesting, alpha and skip-report rules.
*/
#include "test.h"
#include "util.h"
#include "batchrt.h"
#include "../examples/lib/pbrt.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <stdio.h>

#define PI_ 3.14159265358979323846

/* ---- the model: 4x4 matrices, pbrt's conventions --------------------- */

typedef struct m4 { double m[4][4]; } m4;

static m4 m4_identity(void)
{
    m4 a;
    int i, j;
    for (i = 0; i < 4; i++) for (j = 0; j < 4; j++) a.m[i][j] = i == j;
    return a;
}

static m4 m4_mul(m4 a, m4 b)
{
    m4 c;
    int i, j, k;
    for (i = 0; i < 4; i++)
        for (j = 0; j < 4; j++) {
            c.m[i][j] = 0;
            for (k = 0; k < 4; k++) c.m[i][j] += a.m[i][k] * b.m[k][j];
        }
    return c;
}

static m4 m4_scale(double x, double y, double z)
{
    m4 a = m4_identity();
    a.m[0][0] = x; a.m[1][1] = y; a.m[2][2] = z;
    return a;
}

/* pbrt's Rotate(theta, axis): Rodrigues' rotation about the unit axis,
** counter-clockwise looking down the axis toward the origin. */
static m4 m4_rotate(double deg, double x, double y, double z)
{
    double l = sqrt(x * x + y * y + z * z), s = sin(deg * PI_ / 180), c = cos(deg * PI_ / 180);
    double a[3], K[3][3], r;
    m4 o = m4_identity();
    int i, j, k;
    a[0] = x / l; a[1] = y / l; a[2] = z / l;
    K[0][0] = 0; K[0][1] = -a[2]; K[0][2] = a[1];
    K[1][0] = a[2]; K[1][1] = 0; K[1][2] = -a[0];
    K[2][0] = -a[1]; K[2][1] = a[0]; K[2][2] = 0;
    for (i = 0; i < 3; i++)
        for (j = 0; j < 3; j++) {   /* R = I + s K + (1 - c) K^2 */
            r = (i == j) + s * K[i][j];
            for (k = 0; k < 3; k++) r += (1 - c) * K[i][k] * K[k][j];
            o.m[i][j] = r;
        }
    return o;
}

static void cross(const double a[3], const double b[3], double o[3])
{
    o[0] = a[1] * b[2] - a[2] * b[1];
    o[1] = a[2] * b[0] - a[0] * b[2];
    o[2] = a[0] * b[1] - a[1] * b[0];
}

static void unit(double v[3])
{
    double l = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    v[0] /= l; v[1] /= l; v[2] /= l;
}

/* pbrt's LookAt: worldFromCamera's columns are right = up x dir,
** newUp = dir x right, dir and the eye; LookAt is its inverse, the
** transpose of the rotation with the eye taken off. */
static m4 m4_look_at(const double e[3], const double l[3], const double u[3])
{
    double dir[3], up[3], right[3], nup[3];
    m4 o = m4_identity();
    int k;
    for (k = 0; k < 3; k++) { dir[k] = l[k] - e[k]; up[k] = u[k]; }
    unit(dir);
    unit(up);
    cross(up, dir, right);
    unit(right);
    cross(dir, right, nup);
    for (k = 0; k < 3; k++) {
        o.m[0][k] = right[k];
        o.m[1][k] = nup[k];
        o.m[2][k] = dir[k];
    }
    for (k = 0; k < 3; k++) o.m[k][3] = -(o.m[k][0] * e[0] + o.m[k][1] * e[1] + o.m[k][2] * e[2]);
    return o;
}

/* A camera case: the CTM at Camera (camera-from-world), fov, the film and
** the screen window pbrt-v4 derives from them. */
typedef struct model {
    m4 camera_from_world;
    double fov;
    int width, height;
    double x0, x1, y0, y1;   /* screen window */
} model;

/* PerspectiveCamera::Create: frame = xres / yres unless frameaspectratio;
** the shorter side spans [-1, 1]; a screenwindow replaces it all. */
static void model_film(model *md, int width, int height, double frame, const double *window)
{
    md->width = width;
    md->height = height;
    if (frame <= 0) frame = (double)width / height;
    if (frame > 1) { md->x0 = -frame; md->x1 = frame; md->y0 = -1; md->y1 = 1; }
    else { md->x0 = -1; md->x1 = 1; md->y0 = -1 / frame; md->y1 = 1 / frame; }
    if (window) { md->x0 = window[0]; md->x1 = window[1]; md->y0 = window[2]; md->y1 = window[3]; }
}

/* A world point to raster coordinates (x right, y down, pixels): camera
** space, Perspective's divide by z and scale by 1/tan(fov/2), then raster
** from screen.  0 when the point is not in front of the camera. */
static int model_project(const model *md, const double p[3], double *rx, double *ry)
{
    double c[3], inv = 1 / tan(md->fov * PI_ / 360), sx, sy;
    int i;
    for (i = 0; i < 3; i++)
        c[i] = md->camera_from_world.m[i][0] * p[0] + md->camera_from_world.m[i][1] * p[1]
             + md->camera_from_world.m[i][2] * p[2] + md->camera_from_world.m[i][3];
    if (!(c[2] > 0)) return 0;
    sx = c[0] / c[2] * inv;
    sy = c[1] / c[2] * inv;
    *rx = (sx - md->x0) / (md->x1 - md->x0) * md->width;
    *ry = (md->y1 - sy) / (md->y1 - md->y0) * md->height;
    return 1;
}

/* The eye: where camera space's origin is in the world. */
static void model_eye(const model *md, double eye[3])
{
    /* camera_from_world = [R | t] with R a rotation times a scale of +-1
    ** here: R^-1 = R^T up to those signs, so solve R e = -t directly. */
    const double (*m)[4] = md->camera_from_world.m;
    double det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
               + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    double b[3];
    int i, k;
    for (i = 0; i < 3; i++) b[i] = -m[i][3];
    for (k = 0; k < 3; k++) {   /* Cramer's rule */
        double a[3][3];
        int r, c;
        for (r = 0; r < 3; r++) for (c = 0; c < 3; c++) a[r][c] = c == k ? b[r] : m[r][c];
        eye[k] = (a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1]) - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
                  + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])) / det;
    }
}

/* ---- the cases ------------------------------------------------------- */

typedef struct cam_case {
    const char *name;
    const char *header;      /* the file up to WorldBegin */
    model md;
    double point[3];         /* a world point the end-to-end render looks for */
} cam_case;

static double E1[3] = {0, 0, 10}, O[3] = {0, 0, 0}, YUP[3] = {0, 1, 0};

static void case_yup(cam_case *c, int mirror)
{
    c->name = mirror ? "y-up, Scale -1 1 1" : "y-up, no Scale";
    c->header = mirror ? "Scale -1 1 1\nLookAt 0 0 10  0 0 0  0 1 0\nCamera \"perspective\" \"float fov\" 40\n"
                         "Film \"rgb\" \"integer xresolution\" 40 \"integer yresolution\" 30\n"
                       : "LookAt 0 0 10  0 0 0  0 1 0\nCamera \"perspective\" \"float fov\" 40\n"
                         "Film \"rgb\" \"integer xresolution\" 40 \"integer yresolution\" 30\n";
    c->md.camera_from_world = m4_look_at(E1, O, YUP);
    if (mirror) c->md.camera_from_world = m4_mul(m4_scale(-1, 1, 1), c->md.camera_from_world);
    c->md.fov = 40;
    model_film(&c->md, 40, 30, 0, NULL);
    c->point[0] = 1.5; c->point[1] = 0.8; c->point[2] = 0;
}

static void case_zup_portrait(cam_case *c)
{
    double e[3] = {10, 0, 0}, u[3] = {0, 0, 1};
    c->name = "z-up, portrait";
    c->header = "Scale -1 1 1\nLookAt 10 0 0   0 0 0   0 0 1\nCamera \"perspective\" \"float fov\" 40\n"
                "Film \"rgb\" \"integer xresolution\" 30 \"integer yresolution\" 40\n";
    c->md.camera_from_world = m4_mul(m4_scale(-1, 1, 1), m4_look_at(e, O, u));
    c->md.fov = 40;
    model_film(&c->md, 30, 40, 0, NULL);
    c->point[0] = 0; c->point[1] = -1.0; c->point[2] = 2.2;
}

static void case_rotate(cam_case *c)
{
    c->name = "a Rotate after LookAt";
    c->header = "LookAt 0 0 10  0 0 0  0 1 0\nRotate 30 0 0 1\nRotate 10 0 1 0\n"
                "Camera \"perspective\" \"float fov\" 50\n"
                "Film \"rgb\" \"integer xresolution\" 40 \"integer yresolution\" 30\n";
    c->md.camera_from_world = m4_mul(m4_mul(m4_look_at(E1, O, YUP), m4_rotate(30, 0, 0, 1)), m4_rotate(10, 0, 1, 0));
    c->md.fov = 50;
    model_film(&c->md, 40, 30, 0, NULL);
    c->point[0] = 2.0; c->point[1] = 0.5; c->point[2] = 0;
}

static void case_window(cam_case *c)
{
    static const double w[4] = {-0.5, 1.0, -1.0, 0.25};
    c->name = "a screenwindow";
    c->header = "Scale -1 1 1\nLookAt 0 0 10  0 0 0  0 1 0\n"
                "Camera \"perspective\" \"float fov\" 40 \"float screenwindow\" [-0.5 1 -1 0.25]\n"
                "Film \"rgb\" \"integer xresolution\" 40 \"integer yresolution\" 30\n";
    c->md.camera_from_world = m4_mul(m4_scale(-1, 1, 1), m4_look_at(E1, O, YUP));
    c->md.fov = 40;
    model_film(&c->md, 40, 30, 0, w);
    c->point[0] = 1.2; c->point[1] = -1.5; c->point[2] = 0;
}

static void case_frame(cam_case *c)
{
    c->name = "a frameaspectratio";
    c->header = "Scale -1 1 1\nLookAt 0 0 10  0 0 0  0 1 0\n"
                "Camera \"perspective\" \"float fov\" 40 \"float frameaspectratio\" 0.5\n"
                "Film \"rgb\" \"integer xresolution\" 40 \"integer yresolution\" 30\n";
    c->md.camera_from_world = m4_mul(m4_scale(-1, 1, 1), m4_look_at(E1, O, YUP));
    c->md.fov = 40;
    model_film(&c->md, 40, 30, 0.5, NULL);
    c->point[0] = -1.0; c->point[1] = 3.0; c->point[2] = 0;
}

/* No axis in common: every term of the cross products counts. */
static void case_oblique(cam_case *c)
{
    double e[3] = {3, 4, 7}, l[3] = {0.5, -1, 0.25}, u[3] = {0.2, 1, 0.3};
    c->name = "an oblique LookAt";
    c->header = "Scale -1 1 1\nLookAt 3 4 7  0.5 -1 0.25  0.2 1 0.3\nCamera \"perspective\" \"float fov\" 45\n"
                "Film \"rgb\" \"integer xresolution\" 40 \"integer yresolution\" 30\n";
    c->md.camera_from_world = m4_mul(m4_scale(-1, 1, 1), m4_look_at(e, l, u));
    c->md.fov = 45;
    model_film(&c->md, 40, 30, 0, NULL);
    c->point[0] = 1.1; c->point[1] = -0.6; c->point[2] = 0.4;
}

enum { CASES = 9 };

static void make_cases(cam_case *c)
{
    memset(c, 0, CASES * sizeof *c);
    case_yup(&c[0], 0);
    case_yup(&c[1], 1);
    case_zup_portrait(&c[2]);
    case_rotate(&c[3]);
    case_window(&c[4]);
    case_frame(&c[5]);
    /* landscape film on the z-up camera: fov now spans the height */
    case_zup_portrait(&c[6]);
    c[6].name = "z-up, landscape";
    c[6].header = "Scale -1 1 1\nLookAt 10 0 0   0 0 0   0 0 1\nCamera \"perspective\" \"float fov\" 40\n"
                  "Film \"rgb\" \"integer xresolution\" 40 \"integer yresolution\" 30\n";
    model_film(&c[6].md, 40, 30, 0, NULL);
    case_oblique(&c[7]);
    /* a parameter given twice: the last counts (pbrt-v4's rule), for the
    ** window as for P and indices */
    case_window(&c[8]);
    c[8].name = "a screenwindow given twice";
    c[8].header = "Scale -1 1 1\nLookAt 0 0 10  0 0 0  0 1 0\n"
                  "Camera \"perspective\" \"float fov\" 40 \"float screenwindow\" [-2 2 -2 2]\n"
                  "  \"float screenwindow\" [-0.5 1 -1 0.25]\n"
                  "Film \"rgb\" \"integer xresolution\" 40 \"integer yresolution\" 30\n";
}

static ex_pbrt *open_case(const cam_case *c, const char *name)
{
    char text[1024];
    ex_pbrt *s;
    brt_error err;
    snprintf(text, sizeof text, "%sWorldBegin\n", c->header);
    if (!tu_spill(tu_scratch(name), text, strlen(text))) return NULL;
    if (ex_pbrt_open(tu_scratch(name), &s, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s: %s", c->name, err.message);
        return NULL;
    }
    return s;
}

/* The reader's frame, at the raster point the model gives a world point,
** points straight at it; the eye is the model's. */
static void test_frame_is_the_model(void)
{
    cam_case c[CASES];
    int i, j;
    make_cases(c);
    for (i = 0; i < CASES; i++) {
        ex_pbrt *s = open_case(&c[i], "cam.pbrt");
        double eye[3], f[3], r[3], u[3], me[3], worst = 0;
        uint32_t w, h;
        int k, seen = 0;
        if (!s) return;
        EXPECT(ex_pbrt_film(s, &w, &h) == 1 && (int)w == c[i].md.width && (int)h == c[i].md.height,
               "%s: film %ux%u, expected %dx%d", c[i].name, w, h, c[i].md.width, c[i].md.height);
        CHECK(ex_pbrt_camera_frame(s, w, h, eye, f, r, u), "%s: no camera frame", c[i].name);
        model_eye(&c[i].md, me);
        for (k = 0; k < 3; k++)
            EXPECT(fabs(eye[k] - me[k]) < 1e-9, "%s: eye[%d] %g, the model's %g", c[i].name, k, eye[k], me[k]);
        for (j = 0; j < 125; j++) {   /* a lattice of points around the origin */
            double p[3], rx, ry, d[3], want[3], dot = 0, sx, sy;
            p[0] = (j % 5 - 2) * 1.1;
            p[1] = (j / 5 % 5 - 2) * 0.9;
            p[2] = (j / 25 - 2) * 1.3;
            if (!model_project(&c[i].md, p, &rx, &ry)) continue;
            seen++;
            sx = rx / c[i].md.width;
            sy = ry / c[i].md.height;
            for (k = 0; k < 3; k++) {
                d[k] = f[k] + (2 * sx - 1) * r[k] + (1 - 2 * sy) * u[k];
                want[k] = p[k] - me[k];
            }
            unit(d);
            unit(want);
            for (k = 0; k < 3; k++) dot += d[k] * want[k];
            worst = fmax(worst, acos(fmin(1, dot)));
        }
        EXPECT(seen > 50 && worst < 1e-6, "%s: the ray through the model's raster point of a world point "
               "misses it by %g radians (%d points)", c[i].name, worst, seen);
        ex_pbrt_close(s);
    }
}

/* The facts the issue names, on the model itself, so that the model is
** checked too: a bare LookAt puts world +x on the image's left, Scale -1
** 1 1 on its right; z-up keeps world +z up; fov spans the shorter side. */
static void test_model_facts(void)
{
    cam_case c[CASES];
    double px[3] = {1, 0, 0}, pz[3] = {0, 0, 1}, rx, ry;
    make_cases(c);
    CHECK(model_project(&c[0].md, px, &rx, &ry) && rx < 20, "bare LookAt: +x at raster x %g, not on the left", rx);
    CHECK(model_project(&c[1].md, px, &rx, &ry) && rx > 20, "Scale -1 1 1: +x at raster x %g, not on the right", rx);
    CHECK(model_project(&c[2].md, pz, &rx, &ry) && ry < 20 && fabs(rx - 15) < 1e-9,
          "z-up: world +z at raster (%g, %g), not straight up", rx, ry);
    {   /* the top edge of the shorter side is at fov/2: portrait spans x, landscape y */
        double t = tan(20 * PI_ / 180) * 10, top[3] = {0, 0, 0}, side[3] = {0, 0, 0};
        top[2] = t;
        CHECK(model_project(&c[6].md, top, &rx, &ry) && fabs(ry) < 1e-9, "landscape: fov/2 up at raster y %g", ry);
        side[1] = t;
        CHECK(model_project(&c[2].md, side, &rx, &ry) && (fabs(rx) < 1e-9 || fabs(rx - 30) < 1e-9),
              "portrait: fov/2 aside at raster x %g, not an edge", rx);
    }
}

/* ---- end to end: render lights the model's pixel -------------------- */

/* Two corners spanning the plane facing the eye, around p. */
static void facing_triangle(const double eye[3], const double p[3], double size, char *out, size_t n)
{
    double v[3], a[3], b[3], any[3] = {0.31, 0.93, 0.17}, q[3][3];
    int k, i;
    for (k = 0; k < 3; k++) v[k] = eye[k] - p[k];
    unit(v);
    cross(v, any, a);
    unit(a);
    cross(v, a, b);
    for (i = 0; i < 3; i++) {
        double ang = 2 * PI_ * i / 3;
        for (k = 0; k < 3; k++) q[i][k] = p[k] + size * (cos(ang) * a[k] + sin(ang) * b[k]);
    }
    snprintf(out, n, "[%.9g %.9g %.9g  %.9g %.9g %.9g  %.9g %.9g %.9g]", q[0][0], q[0][1], q[0][2], q[1][0], q[1][1],
             q[1][2], q[2][0], q[2][1], q[2][2]);
}

static unsigned char *render_png(const char *file, const char *extra, int *w, int *h)
{
    unsigned char *png, *rgb = NULL;
    size_t n = 0;
    if (tu_run("render @/%s --spp 1 --direct --grey --no-nee %s --out @/%s.png", file, extra, file) != 0) {
        test_fail_at(__FILE__, __LINE__, "render %s: %s", file, tu_last_stderr());
        return NULL;
    }
    {
        char name[256];
        snprintf(name, sizeof name, "%s.png", file);
        png = tu_slurp(tu_scratch(name), &n);
    }
    if (png) rgb = tu_png_decode(png, n, w, h);
    free(png);
    return rgb;
}

/* Each case drawn by render at its film's size: the pixels that differ
** from the same file with the triangle's "alpha" 0 are the triangle's; the
** model's pixel of its centre is among them, at their centroid.  A
** second triangle behind the eye keeps the scene's bounds alike. */
static void test_render_puts_it_there(void)
{
    cam_case c[CASES];
    int i;
    make_cases(c);
    for (i = 0; i < CASES; i++) {
        double me[3], rx, ry, behind[3], cx = 0, cy = 0;
        char tri[256], back[256], text[2048];
        unsigned char *a, *b;
        int wa = 0, ha = 0, wb = 0, hb = 0, x, y, lit = 0, k, at;
        if (i == 5) continue;   /* frameaspectratio: covered by the frame test */
        model_eye(&c[i].md, me);
        CHECK(model_project(&c[i].md, c[i].point, &rx, &ry) && rx >= 2 && rx <= c[i].md.width - 2 && ry >= 2 &&
                  ry <= c[i].md.height - 2, "%s: the case's point is not well inside the image", c[i].name);
        facing_triangle(me, c[i].point, 0.45, tri, sizeof tri);
        for (k = 0; k < 3; k++) behind[k] = 2 * me[k] - c[i].point[k];
        facing_triangle(me, behind, 0.45, back, sizeof back);
        for (at = 0; at < 2; at++) {
            snprintf(text, sizeof text, "%sWorldBegin\nShape \"trianglemesh\" \"point3 P\" %s\n"
                     "Shape \"trianglemesh\" \"point3 P\" %s \"float alpha\" %s\n",
                     c[i].header, back, tri, at ? "0" : "1");
            CHECK(tu_spill(tu_scratch(at ? "e2e_b.pbrt" : "e2e_a.pbrt"), text, strlen(text)), "cannot write");
        }
        a = render_png("e2e_a.pbrt", "", &wa, &ha);
        b = render_png("e2e_b.pbrt", "", &wb, &hb);
        if (!a || !b) { free(a); free(b); CHECK(0, "%s: no images", c[i].name); }
        if (wa != c[i].md.width || ha != c[i].md.height || wb != wa || hb != ha) {
            free(a); free(b);
            CHECK(0, "%s: images %dx%d and %dx%d, the film is %dx%d", c[i].name, wa, ha, wb, hb, c[i].md.width,
                  c[i].md.height);
        }
        for (y = 0; y < ha; y++)
            for (x = 0; x < wa; x++) {
                size_t o = 3 * ((size_t)y * wa + x);
                if (abs(a[o] - b[o]) + abs(a[o + 1] - b[o + 1]) + abs(a[o + 2] - b[o + 2]) > 6) {
                    lit++;
                    cx += x + 0.5;
                    cy += y + 0.5;
                }
            }
        {
            size_t o = 3 * ((size_t)floor(ry) * wa + (size_t)floor(rx));
            int hit = lit > 0 && abs(a[o] - b[o]) + abs(a[o + 1] - b[o + 1]) + abs(a[o + 2] - b[o + 2]) > 6;
            EXPECT(hit && fabs(cx / lit - rx) < 1.5 && fabs(cy / lit - ry) < 1.5,
                   "%s: the model puts the triangle at raster (%.1f, %.1f); render lit %d pixels around "
                   "(%.1f, %.1f)%s", c[i].name, rx, ry, lit, lit ? cx / lit : -1, lit ? cy / lit : -1,
                   hit ? "" : ", not the model's pixel");
        }
        free(a);
        free(b);
    }
}

/* --width and --height override the film's size. */
static void test_render_size_override(void)
{
    static const char text[] = "Scale -1 1 1\nLookAt 0 0 10  0 0 0  0 1 0\nCamera \"perspective\"\n"
                               "Film \"rgb\" \"integer xresolution\" 40 \"integer yresolution\" 30\n"
                               "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n";
    unsigned char *rgb;
    int w = 0, h = 0;
    CHECK(tu_spill(tu_scratch("size.pbrt"), text, sizeof text - 1), "cannot write");
    rgb = render_png("size.pbrt", "--width 12", &w, &h);
    EXPECT(rgb && w == 12 && h == 30, "--width 12 on a 40x30 film: %dx%d", w, h);
    free(rgb);
    /* The variants of the default size: a Camera and no Film is pbrt-v4's
    ** 1280x720; a Film and no Camera is the Film's size. */
    {
        static const char camera_only[] = "LookAt 0 0 10  0 0 0  0 1 0\nCamera \"perspective\"\n"
                                          "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n";
        static const char film_only[] = "Film \"rgb\" \"integer xresolution\" 24 \"integer yresolution\" 10\n"
                                        "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n";
        CHECK(tu_spill(tu_scratch("camera-only.pbrt"), camera_only, sizeof camera_only - 1), "cannot write");
        rgb = render_png("camera-only.pbrt", "", &w, &h);
        EXPECT(rgb && w == 1280 && h == 720, "a Camera and no Film: %dx%d, want pbrt-v4's 1280x720", w, h);
        free(rgb);
        CHECK(tu_spill(tu_scratch("film-only.pbrt"), film_only, sizeof film_only - 1), "cannot write");
        rgb = render_png("film-only.pbrt", "", &w, &h);
        EXPECT(rgb && w == 24 && h == 10, "a Film of 24x10 and no Camera: %dx%d", w, h);
        free(rgb);
    }
}

/* raygen --kind camera on a pbrt file: one ray per pixel centre of the
** film, in raster order, from the model's eye toward the model's pixel. */
static void test_raygen_pixel_centres(void)
{
    cam_case c[CASES];
    brt_ray *rays = NULL;
    size_t n = 0, i;
    double me[3];
    brt_error err;
    char text[1024];
    make_cases(c);
    snprintf(text, sizeof text, "%sWorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n",
             c[3].header);
    CHECK(tu_spill(tu_scratch("rg.pbrt"), text, strlen(text)), "cannot write");
    CHECK(tu_run("raygen @/rg.pbrt @/rg.rays --kind camera") == 0, "raygen: %s", tu_last_stderr());
    CHECK(brt_rays_read(tu_scratch("rg.rays"), &rays, &n, &err) == BRT_OK, "%s", err.message);
    EXPECT(n == 40 * 30, "%zu rays for a 40x30 film", n);
    model_eye(&c[3].md, me);
    for (i = 0; i < n && i < 40 * 30; i++) {
        /* the point one unit along the ray must project to pixel i's centre */
        double p[3], rx = -1, ry = -1;
        int k;
        for (k = 0; k < 3; k++) p[k] = rays[i].org[k] + 3.0 * rays[i].dir[k];
        if (fabs(rays[i].org[0] - me[0]) + fabs(rays[i].org[1] - me[1]) + fabs(rays[i].org[2] - me[2]) > 1e-5 ||
            !model_project(&c[3].md, p, &rx, &ry) || fabs(rx - (double)(i % 40 + 0.5)) > 1e-3 ||
            fabs(ry - (double)(i / 40 + 0.5)) > 1e-3) {
            test_fail_at(__FILE__, __LINE__, "ray %zu: toward raster (%g, %g), expected pixel (%zu, %zu)'s centre", i,
                         rx, ry, i % 40, i / 40);
            break;
        }
    }
    free(rays);
}

/* ---- the reader's rules: nesting, alpha, the skip report ----------- */

static ex_pbrt *open_text(const char *name, const char *text, brt_error *err)
{
    ex_pbrt *s = NULL;
    if (!tu_spill(tu_scratch(name), text, strlen(text))) return NULL;
    if (ex_pbrt_open(tu_scratch(name), &s, err) != BRT_OK) return NULL;
    return s;
}

/* Each block closes with its own End, naming the line of the open one. */
static void test_nesting(void)
{
    static const struct { const char *text, *message; } bad[] = {
        {"AttributeBegin\nTransformBegin\nAttributeEnd\nTransformEnd\n",
         "nest.pbrt:3: AttributeEnd while the TransformBegin at "},
        {"TransformBegin\nAttributeEnd\n", "nest.pbrt:2: AttributeEnd while the TransformBegin at "},
        {"AttributeBegin\nTransformEnd\n", "nest.pbrt:2: TransformEnd while the AttributeBegin at "},
        {"WorldBegin\nTransformEnd\n", "nest.pbrt:2: TransformEnd without TransformBegin"},
        {"WorldBegin\n\nTransformBegin\n", "nest.pbrt:3: TransformBegin never closed"},
        {"ObjectBegin \"a\"\nTransformEnd\n", "nest.pbrt:2: TransformEnd while the ObjectBegin at "}};
    size_t i;
    brt_error err;
    ex_pbrt *s;
    for (i = 0; i < sizeof bad / sizeof *bad; i++) {
        err.message[0] = 0;
        s = open_text("nest.pbrt", bad[i].text, &err);
        EXPECT(!s && strstr(err.message, bad[i].message), "case %zu: \"%s\", expected \"%s...\"", i,
               s ? "(accepted)" : err.message, bad[i].message);
        if (s) ex_pbrt_close(s);
    }
    s = open_text("nest.pbrt", "TransformBegin\nAttributeBegin\nAttributeEnd\nTransformEnd\nWorldBegin\n"
                               "Shape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\nWorldEnd\n", &err);
    CHECK(s, "well nested: %s", err.message);
    EXPECT(strcmp(ex_pbrt_skipped(s), "skipped: 1 WorldEnd") == 0, "summary \"%s\"", ex_pbrt_skipped(s));
    ex_pbrt_close(s);
}

#define TRI "Shape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]"

/* A constant alpha of 0 removes the shape (world or object), counted;
** 1 keeps it silently; another constant or a texture keeps it, reported. */
static void test_alpha(void)
{
    brt_error err;
    uint64_t world;
    uint32_t protos, inst;
    ex_pbrt *s = open_text("alpha.pbrt",
        "WorldBegin\n" TRI " \"float alpha\" 0\n" TRI " \"float alpha\" [ 0 ]\n" TRI " \"float alpha\" 1\n"
        TRI " \"float alpha\" 0.5\n" TRI " \"texture alpha\" \"leaves\"\n" TRI "\n"
        "ObjectBegin \"o\"\n" TRI " \"float alpha\" 0\n" TRI "\nObjectEnd\nObjectInstance \"o\"\n", &err);
    CHECK(s, "%s", err.message);
    ex_pbrt_counts(s, &world, &protos, &inst);
    EXPECT(world == 4, "%llu world shapes kept, expected 4 (two of alpha 0 removed)", (unsigned long long)world);
    EXPECT(strcmp(ex_pbrt_skipped(s), "skipped: 3 Shape removed by \"alpha\" 0, "
                  "1 Shape parameter \"alpha\" (kept opaque), 1 Shape parameter \"texture alpha\" (kept opaque)") == 0,
           "summary \"%s\"", ex_pbrt_skipped(s));
    EXPECT(protos == 1 && inst == 1, "%u prototypes, %u instances", protos, inst);
    ex_pbrt_close(s);
}

/* Every dropped parameter of a shape, the camera and the film, counted
** by name, in one line on stderr and in --stats. */
static void test_skip_report(void)
{
    static const char text[] =
        "LookAt 0 0 5  0 0 0  0 1 0\nCamera \"perspective\" \"float lensradius\" 0.1 \"float fov\" 30\n"
        "Film \"rgb\" \"string filename\" \"x.exr\" \"integer xresolution\" 8 \"integer yresolution\" 8\n"
        "WorldBegin\n"
        TRI " \"point2 uv\" [0 0 1 0 0 1] \"normal N\" [0 0 1 0 0 1 0 0 1]\n"
        TRI " \"vector3 S\" [1 0 0 1 0 0 1 0 0] \"point2 uv\" [0 0 1 0 0 1] \"texture alpha\" \"t\"\n";
    const char *want = "skipped: 1 Camera parameter \"lensradius\", 1 Film parameter \"filename\", "
                       "2 Shape parameter \"uv\", 1 Shape parameter \"N\", 1 Shape parameter \"S\", "
                       "1 Shape parameter \"texture alpha\" (kept opaque)";
    char *json, *err_text;
    brt_error err;
    ex_pbrt *s = open_text("report.pbrt", text, &err);
    CHECK(s, "%s", err.message);
    EXPECT(strcmp(ex_pbrt_skipped(s), want) == 0, "summary\n  \"%s\"\nexpected\n  \"%s\"", ex_pbrt_skipped(s), want);
    ex_pbrt_close(s);
    CHECK(tu_run("raygen @/report.pbrt @/report.rays --kind camera") == 0, "raygen: %s", tu_last_stderr());
    CHECK(tu_run("trace @/report.pbrt @/report.rays @/report.hits --stats @/report.json") == 0, "trace: %s",
          tu_last_stderr());
    err_text = tu_last_stderr();
    /* the whole summary on one line: the line ends where the summary does */
    EXPECT(err_text && strstr(err_text, want) && strchr(strstr(err_text, want), '\n') == strstr(err_text, want) + strlen(want),
           "stderr: %s", err_text ? err_text : "(none)");
    free(err_text);
    json = (char *)tu_slurp(tu_scratch("report.json"), NULL);
    EXPECT(json && strstr(json, "2 Shape parameter \\\"uv\\\", 1 Shape parameter \\\"N\\\""), "statistics: %s",
           json ? json : "(none)");
    free(json);
}

void suite_pbrt_camera(void)
{
    test_run("pbrt camera: the model's facts (handedness, up, fov side)", test_model_facts);
    test_run("pbrt camera: the reader's frame is pbrt-v4's camera", test_frame_is_the_model);
    test_run("pbrt camera: render lights the model's pixel", test_render_puts_it_there);
    test_run("pbrt camera: --width and --height override the film", test_render_size_override);
    test_run("pbrt camera: raygen's pixel centres in raster order", test_raygen_pixel_centres);
    test_run("pbrt reader: blocks close with their own End; WorldEnd reported", test_nesting);
    test_run("pbrt reader: alpha 0 removes a shape, others kept and reported", test_alpha);
    test_run("pbrt reader: every dropped parameter named, in one line and --stats", test_skip_report);
}
