/*
** tests/test_pbrt.c -- the pbrt-v4 scene reader (examples/lib/pbrt.c): each
** test writes small scene files into the scratch folder and checks the
** parsed data itself -- the streamed world triangles, prototypes and
** instances (a point through an instance's transform against pbrt's
** order, CTM = CTM * T), the camera, the skipped-directive summary -- and
** that every error names the file and line.  The library's instanced
** direct mode is not used: world-only files are checked for hits against
** the same triangles read from an OBJ, through brt_bvh.
*/
#include "test.h"
#include "util.h"
#include "batchrt.h"
#include "../examples/lib/pbrt.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <stdio.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

/* ---- helpers --------------------------------------------------------- */

static ex_pbrt *open_text(const char *name, const char *text)
{
    ex_pbrt *scene;
    brt_error err;
    brt_result r = ex_pbrt_open(tu_put(name, text), &scene, &err);
    if (r != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s: %s", name, err.message);
        return NULL;
    }
    return scene;
}

/* Triangles as streamed: corners, and whether chunks were numbered right. */
typedef struct tris {
    float *c;
    uint32_t n, chunks;
    size_t cap;
    int bad_first;
} tris;

static brt_result collect(void *user, const float *corners, uint32_t count, uint32_t first,
                          brt_error *err)
{
    tris *t = user;
    (void)err;
    if (first != t->n) t->bad_first = 1;
    if (!(t->c = brt_grow(t->c, &t->cap, 9 * ((size_t)t->n + count), sizeof *t->c))) return BRT_ENOMEM;
    memcpy(t->c + 9 * (size_t)t->n, corners, 9 * (size_t)count * sizeof *corners);
    t->n += count;
    t->chunks++;
    return BRT_OK;
}

/* The world triangles of scene (0 on a stream error, which fails the test). */
static int world(const ex_pbrt *scene, tris *t)
{
    brt_scene_source src;
    brt_error err;
    memset(t, 0, sizeof *t);
    ex_pbrt_source(scene, &src);
    if (!src.world.run) return 1;
    if (src.world.run(src.world.user, collect, t, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "world stream: %s", err.message);
        return 0;
    }
    EXPECT(!t->bad_first, "chunks not numbered in order");
    return !t->bad_first;
}

static int prototype(const ex_pbrt *scene, uint32_t id, tris *t)
{
    brt_scene_source src;
    brt_error err;
    memset(t, 0, sizeof *t);
    ex_pbrt_source(scene, &src);
    if (src.prototype(src.user, id, collect, t, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "prototype %u: %s", (unsigned)id, err.message);
        return 0;
    }
    return !t->bad_first;
}

typedef struct insts { brt_instance *v; uint32_t n; size_t cap; } insts;

static brt_result collect_inst(void *user, const brt_instance *in, uint32_t count, uint32_t first,
                               brt_error *err)
{
    insts *s = user;
    (void)err;
    if (first != s->n) return BRT_EARG;
    if (!(s->v = brt_grow(s->v, &s->cap, (size_t)s->n + count, sizeof *s->v))) return BRT_ENOMEM;
    memcpy(s->v + s->n, in, count * sizeof *in);
    s->n += count;
    return BRT_OK;
}

static int instances(const ex_pbrt *scene, insts *s)
{
    brt_scene_source src;
    brt_error err;
    memset(s, 0, sizeof *s);
    ex_pbrt_source(scene, &src);
    if (src.instances(src.user, collect_inst, s, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "instances: %s", err.message);
        return 0;
    }
    return 1;
}

/* Corner k (0..2) of triangle i equals (x, y, z) within tol. */
static int corner_is(const tris *t, uint32_t i, int k, double x, double y, double z, double tol)
{
    const float *c = t->c + 9 * (size_t)i + 3 * k;
    return fabs(c[0] - x) <= tol && fabs(c[1] - y) <= tol && fabs(c[2] - z) <= tol;
}

/* A point through an instance's 3x4 object-to-world transform. */
static void inst_point(const brt_instance *in, const float p[3], double out[3])
{
    int i;
    for (i = 0; i < 3; i++)
        out[i] = in->xform[4 * i] * (double)p[0] + in->xform[4 * i + 1] * (double)p[1]
               + in->xform[4 * i + 2] * (double)p[2] + in->xform[4 * i + 3];
}

/* Opening text must fail with result r and a message containing want. */
static void expect_error(const char *name, const char *text, brt_result r, const char *want)
{
    ex_pbrt *scene = NULL;
    brt_error err;
    brt_result got = ex_pbrt_open(tu_put(name, text), &scene, &err);
    EXPECT(got == r, "%s: result %s, expected %s (%s)", name, brt_result_string(got), brt_result_string(r),
           got == BRT_OK ? "opened" : err.message);
    EXPECT(got == BRT_OK || strstr(err.message, want), "%s: message \"%s\" lacks \"%s\"", name, err.message, want);
    EXPECT(got == BRT_OK || scene == NULL, "%s: *out set on error", name);
    ex_pbrt_close(scene);
}

static const char *tri_at_origin =
    "Shape \"trianglemesh\" \"point3 P\" [0 0 0  1 0 0  0 1 0] \"integer indices\" [0 1 2]\n";

/* ---- shapes ---------------------------------------------------------- */

static void test_trianglemesh(void)
{
    ex_pbrt *s = open_text("mesh.pbrt",
        "WorldBegin\n"
        "Shape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 1 1 0 0 1 0]\n"
        "  \"integer indices\" [0 1 2 0 2 3] \"normal N\" [0 0 1 0 0 1 0 0 1 0 0 1]\n"
        "Translate 0 0 5\n"
        "Shape \"trianglemesh\" \"integer indices\" [2 1 0] \"point P\" [1 2 3 4 5 6 7 8 9]\n");
    tris t;
    uint64_t shapes;
    if (!s) return;
    ex_pbrt_counts(s, &shapes, NULL, NULL);
    EXPECT(shapes == 2, "%llu world shapes, expected 2", (unsigned long long)shapes);
    if (world(s, &t)) {
        EXPECT(t.n == 3, "%u triangles, expected 3", (unsigned)t.n);
        EXPECT(t.n == 3 && corner_is(&t, 0, 0, 0, 0, 0, 0) && corner_is(&t, 0, 1, 1, 0, 0, 0)
               && corner_is(&t, 0, 2, 1, 1, 0, 0) && corner_is(&t, 1, 0, 0, 0, 0, 0)
               && corner_is(&t, 1, 1, 1, 1, 0, 0) && corner_is(&t, 1, 2, 0, 1, 0, 0),
               "first shape's triangles are not (0,1,2), (0,2,3) of P");
        /* P after indices in the file; Translate 0 0 5 applied */
        EXPECT(t.n == 3 && corner_is(&t, 2, 0, 7, 8, 14, 0) && corner_is(&t, 2, 1, 4, 5, 11, 0)
               && corner_is(&t, 2, 2, 1, 2, 8, 0), "second shape's triangle is not P[2], P[1], P[0] + (0,0,5)");
    }
    free(t.c);
    ex_pbrt_close(s);
    /* The first shape's indices before its P: the run reads P to the end
    ** of the file, then seeks back before its window for the indices. */
    if (!(s = open_text("mesh-back.pbrt", "WorldBegin\n"
                        "Shape \"trianglemesh\" \"integer indices\" [2 1 0] \"point3 P\" [1 2 3 4 5 6 7 8 9]\n")))
        return;
    if (world(s, &t))
        EXPECT(t.n == 1 && corner_is(&t, 0, 0, 7, 8, 9, 0) && corner_is(&t, 0, 1, 4, 5, 6, 0)
               && corner_is(&t, 0, 2, 1, 2, 3, 0), "indices before P: %u triangles, not P[2], P[1], P[0]",
               (unsigned)t.n);
    free(t.c);
    ex_pbrt_close(s);
}

/* The file NAME holding TEXT streams one world triangle, (0,0,0) (2,0,0)
** (0,3,0); WHAT names the case in the message. */
static void expect_one_triangle(const char *name, const char *text, const char *what)
{
    ex_pbrt *s = open_text(name, text);
    tris t;
    if (!s) return;
    if (world(s, &t))
        EXPECT(t.n == 1 && corner_is(&t, 0, 0, 0, 0, 0, 0) && corner_is(&t, 0, 1, 2, 0, 0, 0)
               && corner_is(&t, 0, 2, 0, 3, 0, 0), "%s: %u triangles, not (0,0,0) (2,0,0) (0,3,0)", what,
               (unsigned)t.n);
    free(t.c);
    ex_pbrt_close(s);
}

/* A parameter given twice: the last counts (pbrt-v4's rule), P and
** indices alike. */
static void test_repeated_parameter(void)
{
    expect_one_triangle("twice.pbrt", "WorldBegin\n"
                        "Shape \"trianglemesh\" \"point3 P\" [9 9 9 9 9 9 9 9 9 9 9 9] \"integer indices\" [3 2 1]\n"
                        "  \"point3 P\" [0 0 0 2 0 0 0 3 0] \"integer indices\" [0 1 2]\n",
                        "P and indices given twice");
}

static void test_three_points(void)
{
    expect_one_triangle("three.pbrt", "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 2 0 0 0 3 0]\n",
                        "3 points without indices");
}

static void test_bilinear(void)
{
    /* p00 = (0,0,0), p10 = (1,0,0), p01 = (0,1,0), p11 = (1,1,0) */
    ex_pbrt *s = open_text("bilinear.pbrt",
        "WorldBegin\nShape \"bilinearmesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0 1 1 0] \"integer indices\" [0 1 2 3]\n"
        "Shape \"bilinearmesh\" \"point3 P\" [0 0 1 1 0 1 0 1 1 1 1 1]\n");
    tris t;
    if (!s) return;
    if (world(s, &t)) {
        EXPECT(t.n == 4, "%u triangles, expected 2 per patch", (unsigned)t.n);
        EXPECT(t.n == 4 && corner_is(&t, 0, 0, 0, 0, 0, 0) && corner_is(&t, 0, 1, 1, 0, 0, 0)
               && corner_is(&t, 0, 2, 1, 1, 0, 0), "first triangle is not (p00, p10, p11)");
        EXPECT(t.n == 4 && corner_is(&t, 1, 0, 0, 0, 0, 0) && corner_is(&t, 1, 1, 1, 1, 0, 0)
               && corner_is(&t, 1, 2, 0, 1, 0, 0), "second triangle is not (p00, p11, p01)");
        EXPECT(t.n == 4 && corner_is(&t, 3, 2, 0, 1, 1, 0), "4 points without indices: not one patch");
    }
    free(t.c);
    ex_pbrt_close(s);
}

static const char *small_ply =
    "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
    "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
    "0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2\n3 0 2 3\n";

static void test_plymesh(void)
{
    ex_pbrt *s;
    tris t;
    tu_put("plydir/quad.ply", small_ply);
    s = open_text("plydir/ply.pbrt",
        "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n"
        "Scale 2 2 2\nShape \"plymesh\" \"string filename\" \"quad.ply\"\n");
    if (!s) return;
    if (world(s, &t)) {
        EXPECT(t.n == 3, "%u triangles, expected 1 + 2", (unsigned)t.n);
        EXPECT(t.n == 3 && corner_is(&t, 1, 2, 2, 2, 0, 0) && corner_is(&t, 2, 2, 0, 2, 0, 0),
               "PLY triangles not numbered after the first shape, or not scaled by 2");
    }
    free(t.c);
    ex_pbrt_close(s);
}

static int count_entries(const char *dir)
{
    return tu_dir_entries(dir, NULL, NULL, NULL, 0);
}

static void test_plymesh_gz(void)
{
    char cmd[1200], tmp[512];
    const char *old = getenv("TMPDIR");
    char saved[512];
    ex_pbrt *s;
    tris t;
    if (system("gzip --version > /dev/null 2>&1") != 0) { test_skip("no gzip on this system"); return; }
    tu_put("gz/quad.ply", small_ply);
    snprintf(cmd, sizeof cmd, "gzip -f '%s'", tu_scratch("gz/quad.ply"));
    CHECK(system(cmd) == 0, "gzip failed");
    snprintf(tmp, sizeof tmp, "%s", tu_scratch("gztmp"));
    mkdir(tmp, 0700);
    s = open_text("gz/gz.pbrt", "WorldBegin\nShape \"plymesh\" \"string filename\" \"quad.ply.gz\"\n");
    if (!s) return;
    snprintf(saved, sizeof saved, "%s", old ? old : "");
    setenv("TMPDIR", tmp, 1);
    if (world(s, &t))
        EXPECT(t.n == 2 && corner_is(&t, 1, 2, 0, 1, 0, 0), "%u triangles from quad.ply.gz, expected 2", (unsigned)t.n);
    EXPECT(count_entries(tmp) == 0, "the temporary file was left in $TMPDIR");
    free(t.c);
    ex_pbrt_close(s);
    /* a file that is not gzip: an error, and the temporary file removed too */
    tu_put("gz/bad.ply.gz", "not gzip");
    s = open_text("gz/bad.pbrt", "WorldBegin\nShape \"plymesh\" \"string filename\" \"bad.ply.gz\"\n");
    if (s) {
        brt_scene_source src;
        brt_error err;
        memset(&t, 0, sizeof t);
        ex_pbrt_source(s, &src);
        EXPECT(src.world.run(src.world.user, collect, &t, &err) == BRT_EIO && strstr(err.message, "gzip"),
               "a bad .gz did not fail with a gzip message");
        EXPECT(count_entries(tmp) == 0, "the temporary file was left after a failure");
        free(t.c);
        ex_pbrt_close(s);
    }
    if (old) setenv("TMPDIR", saved, 1);
    else unsetenv("TMPDIR");
}

/* ---- transforms ------------------------------------------------------ */

/* The one triangle of a file: its first corner (the shape's (0,0,0)... ) */
static int first_triangle(const char *name, const char *text, tris *t)
{
    ex_pbrt *s = open_text(name, text);
    int ok;
    memset(t, 0, sizeof *t);
    if (!s) return 0;
    ok = world(s, t) && t->n >= 1;
    ex_pbrt_close(s);
    EXPECT(ok, "%s: no triangle", name);
    return ok;
}

static void test_translate_rotate_scale(void)
{
    tris t;
    /* CTM = T * R * S: (1,0,0) -> S (2,0,0) -> R 90 about z (0,2,0) -> T (1,2,0) */
    if (first_triangle("trs.pbrt", "WorldBegin\nTranslate 1 0 0\nRotate 90 0 0 1\nScale 2 1 1\n"
                       "Shape \"trianglemesh\" \"point3 P\" [1 0 0 0 0 0 0 1 0]\n", &t))
        EXPECT(corner_is(&t, 0, 0, 1, 2, 0, 1e-6) && corner_is(&t, 0, 1, 1, 0, 0, 1e-6)
               && corner_is(&t, 0, 2, 0, 0, 0, 1e-6),
               "T R S order: (1,0,0) went to (%g,%g,%g), expected (1,2,0)", t.c[0], t.c[1], t.c[2]);
    free(t.c);
    /* Rotate about a non-unit axis is about the unit axis */
    if (first_triangle("rot.pbrt", "WorldBegin\nRotate 90 2 0 0\n"
                       "Shape \"trianglemesh\" \"point3 P\" [0 1 0 0 0 0 1 0 0]\n", &t))
        EXPECT(corner_is(&t, 0, 0, 0, 0, 1, 1e-6), "Rotate 90 about x: (0,1,0) went to (%g,%g,%g), expected (0,0,1)",
               t.c[0], t.c[1], t.c[2]);
    free(t.c);
}

static void test_transform_matrix(void)
{
    tris t;
    /* pbrt lists the matrix column by column: translation is numbers 13..15 */
    if (first_triangle("matrix.pbrt", "WorldBegin\nTranslate 100 0 0\n"
                       "Transform [0 1 0 0  -1 0 0 0  0 0 1 0  5 6 7 1]\n"
                       "Shape \"trianglemesh\" \"point3 P\" [1 0 0 0 0 0 0 1 0]\n", &t)) {
        /* columns: x -> (0,1,0), y -> (-1,0,0); Transform replaces the CTM */
        EXPECT(corner_is(&t, 0, 0, 5, 7, 7, 0) && corner_is(&t, 0, 2, 4, 6, 7, 0),
               "Transform: (1,0,0) went to (%g,%g,%g), expected (5,7,7)", t.c[0], t.c[1], t.c[2]);
    }
    free(t.c);
    if (first_triangle("concat.pbrt", "WorldBegin\nTranslate 100 0 0\n"
                       "ConcatTransform [2 0 0 0  0 2 0 0  0 0 2 0  1 0 0 1]\n"
                       "Shape \"trianglemesh\" \"point3 P\" [1 0 0 0 0 0 0 1 0]\n", &t))
        EXPECT(corner_is(&t, 0, 0, 103, 0, 0, 0), "ConcatTransform: (1,0,0) went to (%g,%g,%g), expected (103,0,0)",
               t.c[0], t.c[1], t.c[2]);
    free(t.c);
    if (first_triangle("identity.pbrt", "WorldBegin\nTranslate 100 0 0\nIdentity\nTranslate 0 1 0\n"
                       "Shape \"trianglemesh\" \"point3 P\" [1 0 0 0 0 0 0 1 0]\n", &t))
        EXPECT(corner_is(&t, 0, 0, 1, 1, 0, 0), "Identity did not reset the CTM");
    free(t.c);
    expect_error("projective.pbrt", "WorldBegin\nTransform [1 0 0 0 0 1 0 0 0 0 1 1 0 0 0 1]\n", BRT_EPARSE,
                 "projective.pbrt:2: only affine");
}

static void test_attribute_blocks(void)
{
    tris t;
    if (first_triangle("blocks.pbrt", "WorldBegin\nTranslate 1 0 0\n"
                       "AttributeBegin\nTranslate 10 0 0\nAttributeEnd\n"
                       "TransformBegin\nScale 5 5 5\nTransformEnd\n"
                       "Shape \"trianglemesh\" \"point3 P\" [1 0 0 0 0 0 0 1 0]\n", &t))
        EXPECT(corner_is(&t, 0, 0, 2, 0, 0, 0), "AttributeEnd/TransformEnd did not restore the CTM: (%g,%g,%g)",
               t.c[0], t.c[1], t.c[2]);
    free(t.c);
    /* transforms under ActiveTransform EndTime leave the start transform alone */
    if (first_triangle("active.pbrt", "WorldBegin\nActiveTransform EndTime\nTranslate 9 9 9\n"
                       "ActiveTransform All\nTranslate 1 0 0\n"
                       "Shape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n", &t))
        EXPECT(corner_is(&t, 0, 0, 1, 0, 0, 0), "an end-time transform moved the shape");
    free(t.c);
}

static void test_coordinate_systems(void)
{
    tris t;
    ex_pbrt *s;
    if (first_triangle("coordsys.pbrt", "WorldBegin\nTranslate 1 0 0\nCoordinateSystem \"a\"\n"
                       "Translate 5 0 0\nCoordSysTransform \"a\"\n"
                       "Shape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n", &t))
        EXPECT(corner_is(&t, 0, 0, 1, 0, 0, 0), "CoordSysTransform did not restore the named CTM");
    free(t.c);
    /* "camera": the world from camera transform, so the origin is the eye */
    if (first_triangle("coordcam.pbrt", "LookAt 1 2 3  1 2 0  0 1 0\nCamera \"perspective\"\nWorldBegin\n"
                       "CoordSysTransform \"camera\"\n"
                       "Shape \"trianglemesh\" \"point3 P\" [0 0 0 0 0 1 0 1 0]\n", &t))
        EXPECT(corner_is(&t, 0, 0, 1, 2, 3, 1e-6) && corner_is(&t, 0, 1, 1, 2, 2, 1e-6),
               "CoordSysTransform \"camera\": origin at (%g,%g,%g), expected the eye (1,2,3)", t.c[0], t.c[1], t.c[2]);
    free(t.c);
    s = open_text("coordunknown.pbrt", "WorldBegin\nCoordSysTransform \"nowhere\"\n");
    if (s) {
        EXPECT(strstr(ex_pbrt_skipped(s), "CoordSysTransform \"nowhere\" (unknown)") != NULL,
               "an unknown coordinate system is not in the summary: \"%s\"", ex_pbrt_skipped(s));
        ex_pbrt_close(s);
    }
}

/* ---- instancing ------------------------------------------------------ */

static void test_instances(void)
{
    ex_pbrt *s = open_text("inst.pbrt",
        "WorldBegin\n"
        "AttributeBegin\nTranslate 1 0 0\n"
        "ObjectBegin \"bush\"\nShape \"trianglemesh\" \"point3 P\" [0 0 0 0 0 1 0 1 0]\nObjectEnd\n"
        "ObjectBegin \"tree\"\n"
        "  Shape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n"
        "  Translate 0 0 3\n"
        "  Shape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n"
        "ObjectEnd\nAttributeEnd\n"
        "Shape \"trianglemesh\" \"point3 P\" [7 7 7 8 7 7 7 8 7]\n"
        "AttributeBegin\nTranslate 5 0 0\nRotate 90 0 0 1\nObjectInstance \"tree\"\nAttributeEnd\n"
        "ObjectInstance \"bush\"\n");
    tris w, p0, p1;
    insts in;
    uint32_t protos, count;
    double q[3];
    if (!s) return;
    ex_pbrt_counts(s, NULL, &protos, &count);
    EXPECT(protos == 2 && count == 2, "%u prototypes, %u instances; expected 2 and 2", (unsigned)protos, (unsigned)count);
    if (world(s, &w))
        EXPECT(w.n == 1 && corner_is(&w, 0, 0, 7, 7, 7, 0), "world: %u triangles, expected only the one outside objects",
               (unsigned)w.n);
    /* prototypes in ObjectBegin order; shapes baked with the CTM at the shape */
    if (prototype(s, 0, &p0))
        EXPECT(p0.n == 1 && corner_is(&p0, 0, 1, 1, 0, 1, 0), "prototype 0 is not bush translated by (1,0,0)");
    if (prototype(s, 1, &p1)) {
        EXPECT(p1.n == 2 && corner_is(&p1, 0, 1, 2, 0, 0, 0) && corner_is(&p1, 1, 0, 1, 0, 3, 0),
               "prototype 1 (tree): not its two shapes with their own CTMs");
    }
    if (instances(s, &in) && in.n == 2 && p1.n == 2) {
        EXPECT(in.v[0].prototype == 1 && in.v[1].prototype == 0, "instance prototypes %u, %u; expected 1, 0",
               (unsigned)in.v[0].prototype, (unsigned)in.v[1].prototype);
        /* pbrt: world = CTM(ObjectInstance) * CTM(shape) * p: (2,0,0) -> R (0,2,0) -> T (5,2,0) */
        inst_point(&in.v[0], p1.c + 3, q);
        EXPECT(fabs(q[0] - 5) < 1e-6 && fabs(q[1] - 2) < 1e-6 && fabs(q[2]) < 1e-6,
               "instance 0 puts (2,0,0) at (%g,%g,%g), expected (5,2,0)", q[0], q[1], q[2]);
        inst_point(&in.v[1], p0.c + 3, q);
        EXPECT(q[0] == 1 && q[1] == 0 && q[2] == 1, "instance 1 is not the identity");
    } else EXPECT(0, "%u instances streamed, expected 2", (unsigned)in.n);
    free(w.c);
    free(p0.c);
    free(p1.c);
    free(in.v);
    ex_pbrt_close(s);
}

static void test_forward_instance(void)
{
    ex_pbrt *s = open_text("forward.pbrt",
        "WorldBegin\nTranslate 0 4 0\nObjectInstance \"later\"\nIdentity\n"
        "ObjectBegin \"first\"\nObjectEnd\nObjectBegin \"later\"\n"
        "Shape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\nObjectEnd\n");
    insts in;
    if (!s) return;
    /* "later" is mentioned first but defined second: prototype 1 */
    if (instances(s, &in))
        EXPECT(in.n == 1 && in.v[0].prototype == 1 && in.v[0].xform[7] == 4,
               "an instance named before its ObjectBegin was not resolved to prototype 1");
    free(in.v);
    ex_pbrt_close(s);
}

/* ---- files ----------------------------------------------------------- */

static void test_include_folder(void)
{
    ex_pbrt *s;
    tris t;
    /* paths in parts/a.pbrt are relative to the main file's folder, not parts/ */
    tu_put("inc/parts/a.pbrt", "Translate 1 0 0\nInclude \"parts/b.pbrt\"\n");
    tu_put("inc/parts/b.pbrt", tri_at_origin);
    tu_put("inc/parts/c.pbrt", "Shape \"trianglemesh\" \"point3 P\" [0 0 9 1 0 9 0 1 9]\n");
    s = open_text("inc/main.pbrt", "WorldBegin\nAttributeBegin\nInclude \"parts/a.pbrt\"\nAttributeEnd\n"
                                   "Import \"parts/c.pbrt\"\n");
    if (!s) return;
    if (world(s, &t))
        EXPECT(t.n == 2 && corner_is(&t, 0, 0, 1, 0, 0, 0) && corner_is(&t, 1, 0, 0, 0, 9, 0),
               "Include/Import: %u triangles or wrong transforms", (unsigned)t.n);
    free(t.c);
    ex_pbrt_close(s);
}

static void test_landscape_layout(void)
{
    ex_pbrt *s;
    tris t;
    float eye[3], target[3], up[3], fov;
    tu_put("landscape/geometry/rocks.ply", small_ply);
    tu_put("landscape/geometry/geometry.pbrt",
        "ObjectBegin \"rock\"\nShape \"plymesh\" \"string filename\" \"geometry/rocks.ply\"\nObjectEnd\n"
        "AttributeBegin\nTranslate 3 0 0\nObjectInstance \"rock\"\nAttributeEnd\n"
        "Shape \"plymesh\" \"string filename\" [ \"geometry/rocks.ply\" ]\n");
    s = open_text("landscape/view-0.pbrt",
        "Scale -1 1 1\nLookAt 0 10 10  0 0 0  0 1 0\nCamera \"perspective\" \"float fov\" [ 40 ]\n"
        "Film \"rgb\" \"integer xresolution\" 1920 \"integer yresolution\" 1080 \"string filename\" \"view-0.exr\"\n"
        "WorldBegin\nInclude \"geometry/geometry.pbrt\"\n");
    if (!s) return;
    if (world(s, &t)) EXPECT(t.n == 2, "world: %u triangles from geometry/rocks.ply, expected 2", (unsigned)t.n);
    free(t.c);
    if (prototype(s, 0, &t)) EXPECT(t.n == 2, "prototype: %u triangles, expected 2", (unsigned)t.n);
    free(t.c);
    EXPECT(ex_pbrt_camera(s, eye, target, up, &fov, NULL) && fov == 40, "the view's camera was not read");
    ex_pbrt_close(s);
}

/* ---- camera ---------------------------------------------------------- */

static void test_camera(void)
{
    float eye[3], target[3], up[3], fov = 0;
    int mirrored = -1;
    ex_pbrt *s = open_text("camera.pbrt",
        "Scale -1 1 1\nLookAt 1 2 3  1 2 -7  0 1 0\nCamera \"perspective\" \"float fov\" 45\nWorldBegin\n");
    if (!s) return;
    CHECK(ex_pbrt_camera(s, eye, target, up, &fov, &mirrored) == 1, "no camera");
    EXPECT(eye[0] == 1 && eye[1] == 2 && eye[2] == 3, "eye (%g,%g,%g), expected (1,2,3)", eye[0], eye[1], eye[2]);
    EXPECT(fabs(target[0] - 1) < 1e-6 && fabs(target[1] - 2) < 1e-6 && fabs(target[2] - 2) < 1e-6,
           "target (%g,%g,%g), expected one unit along -z: (1,2,2)", target[0], target[1], target[2]);
    EXPECT(fabs(up[0]) < 1e-6 && fabs(up[1] - 1) < 1e-6 && fabs(up[2]) < 1e-6, "up (%g,%g,%g)", up[0], up[1], up[2]);
    EXPECT(fov == 45, "fov %g, expected 45", fov);
    EXPECT(mirrored == 0, "Scale -1 1 1 + LookAt: pbrt's right is forward x up, yet mirrored = %d", mirrored);
    ex_pbrt_close(s);
    s = open_text("camera2.pbrt", "LookAt 1 2 3  1 2 -7  0 1 0\nCamera \"perspective\"\nWorldBegin\n");
    if (!s) return;
    CHECK(ex_pbrt_camera(s, eye, target, up, &fov, &mirrored) == 1, "no camera");
    EXPECT(fov == 90, "default fov %g, expected pbrt's 90", fov);
    EXPECT(mirrored == 1, "a bare LookAt (pbrt's left-handed image) should be mirrored");
    ex_pbrt_close(s);
    s = open_text("camera3.pbrt", "Camera \"orthographic\"\nWorldBegin\n");
    if (!s) return;
    EXPECT(ex_pbrt_camera(s, eye, target, up, &fov, NULL) == 0, "an orthographic camera was reported");
    EXPECT(strcmp(ex_pbrt_skipped(s), "skipped: 1 Camera \"orthographic\"") == 0, "summary \"%s\"",
           ex_pbrt_skipped(s));
    ex_pbrt_close(s);
}

/* ---- skipped directives ---------------------------------------------- */

static void test_skipped(void)
{
    ex_pbrt *s = open_text("skipped.pbrt",
        "# a comment \"with a quote\n"
        "Option \"bool disablepixeljitter\" true\nColorSpace \"aces2065-1\"\n"
        "Film \"rgb\" \"integer xresolution\" 640 \"string filename\" [\"a b.exr\"]\n"
        "Sampler \"halton\" \"integer pixelsamples\" 16\nIntegrator \"volpath\" \"integer maxdepth\" [5]\n"
        "PixelFilter \"gaussian\"\nAccelerator \"bvh\"\nTransformTimes 0 1\n"
        "WorldBegin\n"
        "Texture \"checks\" \"spectrum\" \"checkerboard\" \"float uscale\" 8 \"rgb tex1\" [.1 .1 .1]\n"
        "MakeNamedMaterial \"m\" \"string type\" \"diffuse\" \"texture reflectance\" \"checks\"\n"
        "  \"spectrum eta\" \"metal-Cu-eta\" \"blackbody L\" 3000 \"bool remaproughness\" false\n"
        "  \"spectrum k\" [300 .3 800 .6] \"color Kd\" [1 1 1] \"point2 uv\" [0 0]\n"
        "NamedMaterial \"m\"\nMaterial \"conductor\"\nMakeNamedMedium \"fog\" \"string type\" \"homogeneous\"\n"
        "MediumInterface \"fog\" \"\"\nMediumInterface \"fog\"\nAttribute \"shape\" \"float radius\" 2\n"
        "AttributeBegin\nAreaLightSource \"diffuse\" \"blackbody L\" [6500]\nReverseOrientation\n"
        "Shape \"sphere\" \"float radius\" 1\nAttributeEnd\n"
        "AreaLightSource \"diffuse\"\nLightSource \"infinite\" \"string filename\" \"sky.exr\"\n"
        "Shape \"disk\"\nShape \"sphere\"\n"
        "Shape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0] \"float alpha\" 1 \"string emission\" \"x\"\n"
        "WorldEnd\n");
    tris t;
    const char *want = "skipped: 1 Option, 1 ColorSpace, 1 Film parameter \"filename\", 1 Sampler, 1 Integrator, 1 PixelFilter, "
                       "1 Accelerator, 1 TransformTimes, 1 Texture, 1 MakeNamedMaterial, 1 NamedMaterial, "
                       "1 Material, 1 MakeNamedMedium, 2 MediumInterface, 1 Attribute, 2 AreaLightSource, "
                       "1 ReverseOrientation, 2 Shape \"sphere\", 1 LightSource, 1 Shape \"disk\", "
                       "1 Shape parameter \"emission\", 1 WorldEnd";
    if (!s) return;
    EXPECT(strcmp(ex_pbrt_skipped(s), want) == 0, "summary\n  \"%s\"\nexpected\n  \"%s\"", ex_pbrt_skipped(s), want);
    if (world(s, &t)) EXPECT(t.n == 1, "the mesh after skipped directives: %u triangles", (unsigned)t.n);
    free(t.c);
    ex_pbrt_close(s);
    s = open_text("nothing.pbrt", "WorldBegin\n");
    if (s) {
        EXPECT(strcmp(ex_pbrt_skipped(s), "") == 0, "nothing skipped, yet \"%s\"", ex_pbrt_skipped(s));
        ex_pbrt_close(s);
    }
}

/* ---- hits: the same triangles as an OBJ ------------------------------ */

static void test_same_hits_as_obj(void)
{
    uint64_t st = test_seed();
    tu_scene soup = {0};
    size_t cap = 1 << 18, n = 0, i;
    char *pbrt = malloc(cap), *obj = malloc(cap);
    size_t np = 0, no = 0;
    brt_mesh mesh;
    brt_error err;
    brt_bvh *a = NULL, *b = NULL;
    uint32_t *idx = NULL, mismatches = 0, hits = 0;
    float lo[3], hi[3];
    ex_pbrt *s;
    tris t;
    CHECK(pbrt && obj, "out of memory");
    tu_random_soup(&soup, &st, 300, 0.1f);
    tu_scene_transform(&soup, 3.7f, -1.3f);
    /* "%.9g" keeps every float exactly in both files */
    np += (size_t)snprintf(pbrt + np, cap - np, "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [\n");
    for (i = 0; i < soup.vcount; i++) {
        const float *v = soup.pos + 3 * i;
        np += (size_t)snprintf(pbrt + np, cap - np, "%.9g %.9g %.9g\n", v[0], v[1], v[2]);
        no += (size_t)snprintf(obj + no, cap - no, "v %.9g %.9g %.9g\n", v[0], v[1], v[2]);
    }
    np += (size_t)snprintf(pbrt + np, cap - np, "] \"integer indices\" [\n");
    for (i = 0; i < soup.tcount; i++) {
        const uint32_t *f = soup.idx + 3 * i;
        np += (size_t)snprintf(pbrt + np, cap - np, "%u %u %u\n", (unsigned)f[0], (unsigned)f[1], (unsigned)f[2]);
        no += (size_t)snprintf(obj + no, cap - no, "f %u %u %u\n", (unsigned)f[0] + 1, (unsigned)f[1] + 1,
                               (unsigned)f[2] + 1);
    }
    snprintf(pbrt + np, cap - np, "]\n");
    CHECK(np + 200 < cap && no + 200 < cap, "buffers too small");
    tu_put("hits.obj", obj);
    s = open_text("hits.pbrt", pbrt);
    free(pbrt);
    free(obj);
    if (!s) { tu_scene_free(&soup); return; }
    if (!world(s, &t)) { ex_pbrt_close(s); tu_scene_free(&soup); return; }
    ex_pbrt_close(s);
    CHECK(brt_mesh_load(tu_scratch("hits.obj"), &mesh, &err) == BRT_OK, "%s", err.message);
    EXPECT(t.n == mesh.triangle_count, "%u triangles from pbrt, %u from OBJ", (unsigned)t.n, (unsigned)mesh.triangle_count);
    idx = malloc(3 * sizeof *idx * (t.n ? t.n : 1));
    for (i = 0; idx && i < 3 * (size_t)t.n; i++) idx[i] = (uint32_t)i;
    if (idx && t.n == mesh.triangle_count && brt_bvh_build(t.c, idx, t.n, NULL, &a) == BRT_OK
        && brt_bvh_build(mesh.positions, mesh.indices, mesh.triangle_count, NULL, &b) == BRT_OK) {
        tu_scene_bounds(&soup, lo, hi);
        for (i = 0; i < 4000; i++) {
            brt_ray ray;
            brt_hit ha, hb;
            tu_make_ray(&soup, lo, hi, (int)(i % TU_RAY_KINDS), &st, &ray);
            brt_hit_clear(&ha);
            brt_hit_clear(&hb);
            brt_bvh_intersect(a, &ray, &ha);
            brt_bvh_intersect(b, &ray, &hb);
            if (memcmp(&ha, &hb, sizeof ha) != 0) mismatches++;
            hits += hb.prim != BRT_NO_PRIM;
        }
        EXPECT(mismatches == 0, "%u of 4000 rays hit differently in the pbrt and OBJ triangles", (unsigned)mismatches);
        EXPECT(hits > 100, "only %u rays hit: the comparison says little", (unsigned)hits);
    } else EXPECT(0, "could not build the BVHs");
    n = t.n;
    (void)n;
    brt_bvh_free(a);
    brt_bvh_free(b);
    free(idx);
    free(t.c);
    brt_mesh_free(&mesh);
    tu_scene_free(&soup);
}

/* A mesh of more than one chunk: chunks of 65536 numbered in order, the
** same bytes on a second run; a file changed after open is BRT_EIO. */
static void test_chunks_and_reruns(void)
{
    const uint32_t quads = 40000;   /* 80000 triangles */
    size_t cap = (size_t)quads * 80 + 256, n = 0;
    char *text = malloc(cap);
    ex_pbrt *s;
    tris t1, t2;
    uint32_t q;
    CHECK(text, "out of memory");
    n += (size_t)snprintf(text, cap, "WorldBegin\nShape \"bilinearmesh\" \"integer indices\" [");
    for (q = 0; q < quads; q++)
        n += (size_t)snprintf(text + n, cap - n, " %u %u %u %u", 4 * q, 4 * q + 1, 4 * q + 2, 4 * q + 3);
    n += (size_t)snprintf(text + n, cap - n, "]\n\"point3 P\" [");
    for (q = 0; q < quads; q++)
        n += (size_t)snprintf(text + n, cap - n, " %u 0 0 %u 1 0 %u 0 1 %u 1 1", q, q, q, q);
    snprintf(text + n, cap - n, "]\n");
    s = open_text("chunks.pbrt", text);
    free(text);
    if (!s) return;
    if (world(s, &t1) && world(s, &t2)) {
        EXPECT(t1.n == 2 * quads && t1.chunks == 2, "%u triangles in %u chunks, expected %u in 2", (unsigned)t1.n,
               (unsigned)t1.chunks, (unsigned)(2 * quads));
        EXPECT(t1.n == t2.n && memcmp(t1.c, t2.c, 9 * sizeof(float) * t1.n) == 0, "a second run gave other triangles");
        EXPECT(t1.n == 2 * quads && corner_is(&t1, 2 * quads - 1, 1, quads - 1, 1, 1, 0), "the last triangle is wrong");
    }
    free(t1.c);
    free(t2.c);
    /* the file shrinks under the reader: an I/O error, not a wrong triangle */
    tu_put("chunks.pbrt", "WorldBegin\n");
    {
        brt_scene_source src;
        brt_error err;
        memset(&t1, 0, sizeof t1);
        ex_pbrt_source(s, &src);
        EXPECT(src.world.run(src.world.user, collect, &t1, &err) == BRT_EIO, "a changed file was not noticed");
        free(t1.c);
    }
    ex_pbrt_close(s);
}

/* Numbers read as strtof reads them (pbrt reads floats): random decimals
** of every form -- signs, leading and trailing points, long mantissas,
** exponents -- as a P array, against strtof of the same text. */
static void test_numbers_as_strtof(void)
{
    static const char *const fixed[] = {"1.", ".5", "-0", "+2.5e-3", "0.1", "16777217", "3.4028235e38",
                                        "1e-45", "1.17549435e-38", "0.000000000000000000000000000001",
                                        "123456789012345678901234567890", "7.038531e-26", "33554431",
                                        /* past 18 significant digits, leading zeros */
                                        "0.00012345678901234567890123", "1.23456789012345678901234",
                                        "12345678901234567.5", "00000.5", "-000123.4500", "9.99999999999999999999e37"};
    const size_t count = 3000;
    size_t cap = count * 48 + 256, n = 0, i, nf = sizeof fixed / sizeof *fixed;
    char *text = malloc(cap), (*words)[40] = malloc(count * sizeof *words);
    uint64_t st = test_seed();
    uint32_t bad = 0;
    ex_pbrt *s;
    tris t;
    CHECK(text && words, "out of memory");
    for (i = 0; i < count; i++) {
        uint64_t r = brt_random_u64(&st);
        if (i < nf) snprintf(words[i], sizeof words[i], "%s", fixed[i]);
        else if (r % 3 == 0) snprintf(words[i], sizeof words[i], "%.*g", 1 + (int)(r >> 8) % 17,
                                      (double)(brt_random_float(&st) - 0.5f) * pow(10, (int)(r >> 16) % 60 - 30));
        else if (r % 3 == 1) snprintf(words[i], sizeof words[i], "%s%llu.%llue%d", (r >> 7) & 1 ? "-" : "",
                                      (unsigned long long)(brt_random_u64(&st) % 100000000000ull),
                                      (unsigned long long)(brt_random_u64(&st) % 1000000000ull), (int)(r >> 20) % 40 - 20);
        else snprintf(words[i], sizeof words[i], "%.9g", (double)(brt_random_float(&st) * 1000 - 500));
    }
    n += (size_t)snprintf(text, cap, "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [");
    for (i = 0; i < count; i++) n += (size_t)snprintf(text + n, cap - n, " %s", words[i]);
    n += (size_t)snprintf(text + n, cap - n, " ] \"integer indices\" [");
    for (i = 0; i < count / 9 * 3; i++) n += (size_t)snprintf(text + n, cap - n, " %u", (unsigned)i);
    snprintf(text + n, cap - n, " ]\n");
    s = open_text("numbers.pbrt", text);
    free(text);
    if (s && world(s, &t) && t.n == count / 9) {
        for (i = 0; i < count / 9 * 9; i++) {   /* the vertices the triangles use */
            float want = strtof(words[i], NULL);
            if (memcmp(&want, &t.c[i], sizeof want) != 0 && bad++ < 5)
                EXPECT(0, "'%s' read as %.9g, strtof gives %.9g", words[i], t.c[i], want);
        }
        free(t.c);
    } else EXPECT(0, "the numbers did not come back as %u triangles", (unsigned)(count / 9));
    free(words);
    ex_pbrt_close(s);
}

/* ---- errors ---------------------------------------------------------- */

static void test_structure_errors(void)
{
    expect_error("e_directive.pbrt", "WorldBegin\nFrobnicate 1 2\n", BRT_EPARSE,
                 "e_directive.pbrt:2: unknown directive 'Frobnicate'");
    expect_error("e_type.pbrt", "WorldBegin\n\nShape \"trianglemesh\" \"float3 P\" [0 0 0]\n", BRT_EPARSE,
                 "e_type.pbrt:3: unknown parameter type \"float3\"");
    expect_error("e_attrend.pbrt", "WorldBegin\nAttributeBegin\nAttributeEnd\nAttributeEnd\n", BRT_EPARSE,
                 "e_attrend.pbrt:4: AttributeEnd without AttributeBegin");
    expect_error("e_objend.pbrt", "WorldBegin\nObjectEnd\n", BRT_EPARSE, "e_objend.pbrt:2: ObjectEnd without ObjectBegin");
    expect_error("e_open.pbrt", "WorldBegin\nAttributeBegin\nTranslate 1 0 0\n", BRT_EPARSE,
                 "e_open.pbrt:2: AttributeBegin never closed");
    expect_error("e_mixed.pbrt", "WorldBegin\nObjectBegin \"a\"\nAttributeEnd\n", BRT_EPARSE,
                 "e_mixed.pbrt:3: AttributeEnd while the ObjectBegin at");
    expect_error("e_nested.pbrt", "WorldBegin\nObjectBegin \"a\"\nObjectBegin \"b\"\n", BRT_EPARSE,
                 "e_nested.pbrt:3: ObjectBegin \"b\" inside ObjectBegin \"a\"");
    expect_error("e_twice.pbrt", "WorldBegin\nObjectBegin \"a\"\nObjectEnd\nObjectBegin \"a\"\n", BRT_EPARSE,
                 "e_twice.pbrt:4: object \"a\" defined twice");
    expect_error("e_string.pbrt", "WorldBegin\nShape \"trianglemesh\n", BRT_EPARSE, "e_string.pbrt:2: unterminated string");
    {
        ex_pbrt *s;
        brt_error err;
        EXPECT(ex_pbrt_open(tu_scratch("no-such.pbrt"), &s, &err) == BRT_EIO && strstr(err.message, "no-such.pbrt"),
               "a missing main file is not BRT_EIO naming it");
    }
}

static void test_instance_errors(void)
{
    expect_error("e_unknown.pbrt", "WorldBegin\n\nObjectInstance \"tree\"\n", BRT_EPARSE,
                 "e_unknown.pbrt:3: ObjectInstance of unknown object \"tree\"");
    expect_error("e_inside.pbrt", "WorldBegin\nObjectBegin \"a\"\nObjectEnd\nObjectBegin \"b\"\nObjectInstance \"a\"\n",
                 BRT_EPARSE, "e_inside.pbrt:5: ObjectInstance \"a\" inside ObjectBegin \"b\"");
    expect_error("e_singular.pbrt", "WorldBegin\nObjectBegin \"a\"\nObjectEnd\nScale 1 0 1\nObjectInstance \"a\"\n",
                 BRT_EPARSE, "e_singular.pbrt:5: ObjectInstance: singular transform");
    expect_error("e_singshape.pbrt", "WorldBegin\nScale 0 0 0\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n",
                 BRT_EPARSE, "e_singshape.pbrt:3: Shape: singular transform");
}

static void test_include_errors(void)
{
    tu_put("cycle/b.pbrt", "Include \"c.pbrt\"\n");
    tu_put("cycle/c.pbrt", "\nInclude \"b.pbrt\"\n");
    expect_error("cycle/a.pbrt", "WorldBegin\nInclude \"b.pbrt\"\n", BRT_EPARSE, "c.pbrt:2: Include cycle");
    expect_error("e_noinc.pbrt", "WorldBegin\nInclude \"absent/x.pbrt\"\n", BRT_EIO,
                 "e_noinc.pbrt:2: cannot read included file");
    expect_error("e_noply.pbrt", "WorldBegin\nShape \"plymesh\" \"string filename\" \"absent.ply\"\n", BRT_EIO,
                 "e_noply.pbrt:2: plymesh \"absent.ply\": cannot read");
}

static void test_mesh_errors(void)
{
    expect_error("e_p3.pbrt", "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1]\n", BRT_EPARSE,
                 "e_p3.pbrt:2: Shape \"trianglemesh\": \"P\" has 8 numbers, not a multiple of 3");
    expect_error("e_range.pbrt", "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0 1 1 0]\n"
                 "\"integer indices\" [0 1 2\n 0 2 4]\n", BRT_EPARSE,
                 "e_range.pbrt:4: Shape \"trianglemesh\": index 4 out of range (4 vertices)");
    expect_error("e_i3.pbrt", "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0] \"integer indices\" [0 1]\n",
                 BRT_EPARSE, "e_i3.pbrt:2: Shape \"trianglemesh\": \"indices\" has 2 numbers, not a multiple of 3");
    expect_error("e_i4.pbrt", "WorldBegin\nShape \"bilinearmesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0] \"integer indices\" [0 1 2]\n",
                 BRT_EPARSE, "e_i4.pbrt:2: Shape \"bilinearmesh\": \"indices\" has 3 numbers, not a multiple of 4");
    expect_error("e_noidx.pbrt", "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0 1 1 0]\n", BRT_EPARSE,
                 "e_noidx.pbrt:2: Shape \"trianglemesh\": \"indices\" missing");
    expect_error("e_neg.pbrt", "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0] \"integer indices\" [0 -1 2]\n",
                 BRT_EPARSE, "e_neg.pbrt:2: \"indices\": expected a vertex index");
    expect_error("e_inf.pbrt", "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0\n1e39 0 0 0 1 0]\n", BRT_EPARSE,
                 "e_inf.pbrt:3: \"P\": non-finite number '1e39'");
    /* Past FLT_MAX with a short mantissa: the fast path of pass 1 must not take it. */
    expect_error("e_inf2.pbrt", "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 3.5e38 0 0 0 1 0]\n", BRT_EPARSE,
                 "e_inf2.pbrt:2: \"P\": non-finite number '3.5e38'");
    expect_error("e_inf3.pbrt", "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1\n"
                 "1234567890123456789012345678901234567890.5]\n", BRT_EPARSE, "e_inf3.pbrt:3: \"P\": non-finite number");
    expect_error("e_nan.pbrt", "WorldBegin\nTranslate 0 nan 0\n", BRT_EPARSE, "e_nan.pbrt:2: non-finite number 'nan'");
    expect_error("e_num.pbrt", "WorldBegin\nScale 1 x 1\n", BRT_EPARSE, "e_num.pbrt:2: expected a number, got 'x'");
    expect_error("e_noP.pbrt", "WorldBegin\nShape \"trianglemesh\" \"integer indices\" [0 1 2]\n", BRT_EPARSE,
                 "e_noP.pbrt:2: Shape \"trianglemesh\" without \"point3 P\"");
}

/* The fuzz target's findings (tests/corpus/pbrt/crash-*): a name with a
** "\n" escape kept messages and the summary one line; numbers finite in
** float that overflow through a transform refused -- a world shape's
** point (at stream time: pass 1 reads numbers, not points), an
** instance's transform, the camera's position. */
static void test_float_range_and_one_line(void)
{
    ex_pbrt *s;
    brt_scene_source src;
    brt_error err;
    tris t;
    brt_result r;
    expect_error("e_nl.pbrt", "Include \"a\\nb\"\n", BRT_EIO, "e_nl.pbrt:1: cannot read included file");
    expect_error("e_nl.pbrt", "Include \"a\\nb\"\n", BRT_EIO, "a?b");
    expect_error("e_inst_inf.pbrt", "Scale 1e30 1e30 1e30\nScale 1e30 1e30 1e30\nObjectBegin \"a\"\n" "ObjectEnd\n"
                 "ObjectInstance \"a\"\n", BRT_EPARSE, "e_inst_inf.pbrt:5: ObjectInstance: the transform is not finite in float");
    expect_error("e_cam_inf.pbrt", "Translate 1e38 0 0\nScale 1e-38 1 1\nCamera \"perspective\"\n", BRT_EPARSE,
                 "e_cam_inf.pbrt:3: Camera: the camera position is not finite in float");
    if ((s = open_text("e_nl_skip.pbrt", "WorldBegin\nShape \"x\\ny\"\nCoordSysTransform \"p\\rq\"\n")) != NULL) {
        EXPECT(strcmp(ex_pbrt_skipped(s), "skipped: 1 Shape \"x?y\", 1 CoordSysTransform \"p?q\" (unknown)") == 0,
               "summary \"%s\"", ex_pbrt_skipped(s));
        ex_pbrt_close(s);
    }
    s = open_text("e_corner_inf.pbrt", "WorldBegin\n" "Shape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n"
                  "Scale 1e30 1e30 1e30\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1e30 0 0 0 1 0]\n");
    if (!s) return;
    memset(&t, 0, sizeof t);
    ex_pbrt_source(s, &src);
    r = src.world.run(src.world.user, collect, &t, &err);
    EXPECT(r == BRT_EPARSE && strstr(err.message, "e_corner_inf.pbrt:4: Shape: a point is not finite in float"),
           "stream: %s (%s)", brt_result_string(r), r == BRT_OK ? "streamed" : err.message);
    free(t.c);
    ex_pbrt_close(s);
}

/* Counts streamed triangles, nothing kept. */
static brt_result count_only(void *user, const float *corners, uint32_t count, uint32_t first, brt_error *err)
{
    (void)corners;
    (void)first;
    (void)err;
    *(uint64_t *)user += count;
    return BRT_OK;
}

/* What the child of test_bounded_memory reports. */
typedef struct memory_report { uint64_t growth, triangles; int result; } memory_report;

/* The "a 2 GB inline trianglemesh is built in bounded memory,
** never held whole", at tens of MB: 4 vertices and 6.8M triangles of
** indices (40.8 MB).  A forked child (whose peak resident set starts at
** the parent's current one: brt_peak_rss_bytes) opens the file and runs
** its world stream once; its peak grows by what the reader holds (a
** window, one shape's positions, one chunk of 65536 triangles: a few MB),
** and must stay below half the file: a reader holding the file, its
** indices (82 MB) or its triangles (245 MB) fails.  No timing. */
static void test_bounded_memory(void)
{
    enum { PAIRS = 3400000, BLOCK = 100000 };
    static const char pattern[] = "0 1 2 1 3 2\n";   /* two triangles */
    const char *path = tu_scratch("big.pbrt");
    size_t plen = sizeof pattern - 1, i;
    char *block = malloc(BLOCK * plen);
    memory_report rep;
    struct stat st;
    int fds[2], status = -1, ok;
    pid_t pid;
    FILE *f = fopen(path, "wb");
    CHECK(f && block, "cannot write %s", path);
    for (i = 0; i < BLOCK; i++) memcpy(block + i * plen, pattern, plen);
    ok = fputs("WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0 1 1 0]\n\"integer indices\" [\n", f) >= 0;
    for (i = 0; ok && i < PAIRS / BLOCK; i++) ok = fwrite(block, plen, BLOCK, f) == BLOCK;
    ok = fputs("]\n", f) >= 0 && ok;
    free(block);
    CHECK(fclose(f) == 0 && ok && stat(path, &st) == 0, "cannot write %s", path);
    CHECK(pipe(fds) == 0, "pipe");
    fflush(stdout);
    pid = fork();
    if (pid == 0) {
        brt_scene_source src;
        brt_error err;
        ex_pbrt *scene;
        uint64_t before = brt_peak_rss_bytes();
        memset(&rep, 0, sizeof rep);
        rep.result = ex_pbrt_open(path, &scene, &err);
        if (rep.result == BRT_OK) {
            ex_pbrt_source(scene, &src);
            rep.result = src.world.run(src.world.user, count_only, &rep.triangles, &err);
            ex_pbrt_close(scene);
        }
        rep.growth = brt_peak_rss_bytes() - before;
        _exit(write(fds[1], &rep, sizeof rep) == (ssize_t)sizeof rep ? 0 : 1);
    }
    close(fds[1]);
    ok = pid > 0 && read(fds[0], &rep, sizeof rep) == (ssize_t)sizeof rep;
    close(fds[0]);
    if (pid > 0) waitpid(pid, &status, 0);
    unlink(path);
    CHECK(ok && status == 0, "the child did not report");
    if (brt_peak_rss_bytes() == 0) { test_skip("no peak resident set on this system"); return; }
    EXPECT(rep.result == BRT_OK && rep.triangles == 2 * (uint64_t)PAIRS, "result %d, %llu triangles", rep.result,
           (unsigned long long)rep.triangles);
    EXPECT(rep.growth < (uint64_t)st.st_size / 2, "reading a %lld-byte file raised the peak resident set by %llu bytes",
           (long long)st.st_size, (unsigned long long)rep.growth);
}

void suite_pbrt(void)
{
    test_run("pbrt: a parameter given twice: the last counts (P, indices)", test_repeated_parameter);
    test_run("pbrt: trianglemesh: P and indices become world triangles in file order, either first", test_trianglemesh);
    test_run("pbrt: trianglemesh of 3 points without indices", test_three_points);
    test_run("pbrt: bilinearmesh: (p00,p10,p11), (p00,p11,p01)", test_bilinear);
    test_run("pbrt: plymesh through brt_mesh_stream, transformed", test_plymesh);
    test_run("pbrt: plymesh .ply.gz through gzip, temporary file removed", test_plymesh_gz);
    test_run("pbrt: Translate Rotate Scale compose as CTM = CTM * T", test_translate_rotate_scale);
    test_run("pbrt: Transform and ConcatTransform are column by column; Identity", test_transform_matrix);
    test_run("pbrt: AttributeBegin/End, TransformBegin/End, ActiveTransform", test_attribute_blocks);
    test_run("pbrt: CoordinateSystem and CoordSysTransform (camera too)", test_coordinate_systems);
    test_run("pbrt: ObjectBegin prototypes and ObjectInstance transforms", test_instances);
    test_run("pbrt: ObjectInstance before its ObjectBegin", test_forward_instance);
    test_run("pbrt: Include and Import resolve against the main file's folder", test_include_folder);
    test_run("pbrt: landscape layout (view-0.pbrt, geometry/geometry.pbrt, geometry/*.ply)", test_landscape_layout);
    test_run("pbrt: camera from Scale -1 1 1, LookAt and fov", test_camera);
    test_run("pbrt: skipped directives consumed and summarized", test_skipped);
    test_run("pbrt: world triangles hit as the same OBJ's", test_same_hits_as_obj);
    test_run("pbrt: chunks of 65536, reruns, a changed file", test_chunks_and_reruns);
    test_run("pbrt: numbers read as strtof reads them", test_numbers_as_strtof);
    test_run("pbrt: errors: structure", test_structure_errors);
    test_run("pbrt: errors: instances and transforms", test_instance_errors);
    test_run("pbrt: errors: includes and files", test_include_errors);
    test_run("pbrt: errors: mesh data and numbers", test_mesh_errors);
    test_run("pbrt: a 40 MB inline trianglemesh read in bounded memory", test_bounded_memory);
    test_run("pbrt: errors: float overflow through transforms; one-line messages", test_float_range_and_one_line);
}
