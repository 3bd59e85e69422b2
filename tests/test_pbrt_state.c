/*
** tests/test_pbrt_state.c -- the pbrt-v4 reader (examples/lib/pbrt.c) against
** the contract, case by case (issue 38): pbrt-v4's graphics-state rules,
** where error messages point, the chunk thresholds, documented limits and
** the variants of each directive.
**
** The expected placements are derived by hand from pbrt-v4's rules, not
** from our reader: the file format (pbrt.org/fileformat-v4) and, where it
** is silent, pbrt-v4's src/pbrt/parser.cpp and src/pbrt/scene.cpp
** (BasicSceneBuilder), cited per case.  Every case's geometry is put in
** world space through the reader's public API only: the world stream's
** triangles, and each instance's prototype triangles through the
** instance's 3x4 transform (in double), world first, then instances in
** file order.
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

/* ---- helpers --------------------------------------------------------- */

/* Streamed triangles (or instances), with the chunks' numbering checked. */
typedef struct tris { float *c; uint32_t n, chunks, max_chunk; size_t cap; int bad_first; } tris;

static brt_result collect(void *user, const float *corners, uint32_t count, uint32_t first, brt_error *err)
{
    tris *t = user;
    (void)err;
    if (first != t->n) t->bad_first = 1;
    if (!(t->c = brt_grow(t->c, &t->cap, 9 * ((size_t)t->n + count), sizeof *t->c))) return BRT_ENOMEM;
    if (count) memcpy(t->c + 9 * (size_t)t->n, corners, 9 * (size_t)count * sizeof *corners);
    t->n += count;
    t->chunks++;
    if (count > t->max_chunk) t->max_chunk = count;
    return BRT_OK;
}

typedef struct insts { brt_instance *v; uint32_t n, chunks, max_chunk; size_t cap; int bad_first; } insts;

static brt_result collect_inst(void *user, const brt_instance *in, uint32_t count, uint32_t first, brt_error *err)
{
    insts *s = user;
    (void)err;
    if (first != s->n) s->bad_first = 1;
    if (!(s->v = brt_grow(s->v, &s->cap, (size_t)s->n + count + 1, sizeof *s->v))) return BRT_ENOMEM;
    if (count) memcpy(s->v + s->n, in, count * sizeof *in);
    s->n += count;
    s->chunks++;
    if (count > s->max_chunk) s->max_chunk = count;
    return BRT_OK;
}

/* The scene's triangles in world space, as doubles: the world stream's,
** then each instance's prototype triangles through its transform.
** Returns the count, or -1 after recording a failure. */
static long placed(const ex_pbrt *s, double **out)
{
    brt_scene_source src;
    brt_error err;
    tris w, *proto;
    insts in;
    uint32_t i, k, protos;
    size_t n = 0;
    double *c;
    memset(&w, 0, sizeof w);
    memset(&in, 0, sizeof in);
    ex_pbrt_source(s, &src);
    protos = src.prototype_count;
    if (src.world.run && src.world.run(src.world.user, collect, &w, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "world stream: %s", err.message);
        free(w.c);
        return -1;
    }
    if (src.instances(src.user, collect_inst, &in, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "instances: %s", err.message);
        free(w.c);
        free(in.v);
        return -1;
    }
    proto = calloc(protos + 1, sizeof *proto);
    for (i = 0; proto && i < protos; i++)
        if (src.prototype(src.user, i, collect, &proto[i], &err) != BRT_OK)
            test_fail_at(__FILE__, __LINE__, "prototype %u: %s", (unsigned)i, err.message);
    n = w.n;
    for (i = 0; proto && i < in.n; i++) n += in.v[i].prototype < protos ? proto[in.v[i].prototype].n : 0;
    c = malloc((9 * n + 1) * sizeof *c);
    if (c && proto) {
        size_t at = 0;
        for (k = 0; k < 9 * w.n; k++) c[at++] = w.c[k];
        for (i = 0; i < in.n; i++) {
            const brt_instance *x = &in.v[i];
            const tris *p;
            if (x->prototype >= protos) continue;
            p = &proto[x->prototype];
            for (k = 0; k < 3 * p->n; k++) {
                const float *q = p->c + 3 * (size_t)k;
                int r;
                for (r = 0; r < 3; r++)
                    c[at++] = x->xform[4 * r] * (double)q[0] + x->xform[4 * r + 1] * (double)q[1]
                            + x->xform[4 * r + 2] * (double)q[2] + x->xform[4 * r + 3];
            }
        }
    }
    EXPECT(!w.bad_first && !in.bad_first, "chunks not numbered by their first element");
    free(w.c);
    free(in.v);
    for (i = 0; proto && i < protos; i++) free(proto[i].c);
    free(proto);
    *out = c;
    return c ? (long)n : -1;
}

/* Opening text must fail with result r and a message starting with want
** (after the scratch folder: messages name files by their full path). */
static void expect_error(const char *name, const char *text, brt_result r, const char *want)
{
    ex_pbrt *scene = NULL;
    brt_error err;
    brt_result got = ex_pbrt_open(tu_put(name, text), &scene, &err);
    EXPECT(got == r, "%s: result %s, expected %s (%s)", name, brt_result_string(got), brt_result_string(r),
           got == BRT_OK ? "opened" : err.message);
    EXPECT(got == BRT_OK || strstr(err.message, want), "%s: message \"%s\" lacks \"%s\"", name, err.message, want);
    ex_pbrt_close(scene);
}

/* The unit triangle (0,0,0), (1,0,0), (0,1,0): its placement shows where
** the origin, x and y go. */
#define TRI "Shape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n"
/* The unit triangle translated by (x, y, z): the expected corners. */
#define AT(x, y, z) {x, y, z, (x) + 1, y, z, x, (y) + 1, z}

/* ---- 1. graphics-state scoping: a table ------------------------------ */

typedef struct state_case {
    const char *name;       /* the main file, in the scratch folder */
    const char *rule;       /* the pbrt-v4 rule the case demonstrates, and where it is stated */
    const char *text;
    const char *inc_name;   /* a second file (Include, Import), or NULL */
    const char *inc_text;
    int count;              /* triangles placed: world, then instances' */
    double want[3][9];
} state_case;

static const state_case state_cases[] = {
    /* AttributeBegin / AttributeEnd, TransformBegin / TransformEnd */
    {"attr_ctm.pbrt", "fileformat-v4 'Attributes': AttributeEnd restores the CTM saved at AttributeBegin",
     "WorldBegin\nTranslate 1 0 0\nAttributeBegin\nTranslate 10 0 0\n" TRI "AttributeEnd\n" TRI, NULL, NULL,
     2, {AT(11, 0, 0), AT(1, 0, 0)}},
    {"attr_active.pbrt", "scene.cpp AttributeEnd: graphicsState (activeTransformBits too) is restored whole: "
     "an ActiveTransform inside the block does not leak out",
     "WorldBegin\nAttributeBegin\nActiveTransform EndTime\nAttributeEnd\nTranslate 1 0 0\n" TRI, NULL, NULL,
     1, {AT(1, 0, 0)}},
    {"attr_active_in.pbrt", "scene.cpp AttributeEnd: the EndTime in force before the block comes back after it",
     "WorldBegin\nActiveTransform EndTime\nAttributeBegin\nActiveTransform All\nAttributeEnd\nTranslate 1 0 0\n"
     "ActiveTransform All\n" TRI, NULL, NULL, 1, {AT(0, 0, 0)}},
    {"attr_nested.pbrt", "AttributeBegin nests: each AttributeEnd restores its own AttributeBegin's state",
     "WorldBegin\nAttributeBegin\nTranslate 1 0 0\nAttributeBegin\nTranslate 0 1 0\n" TRI "AttributeEnd\n" TRI
     "AttributeEnd\n" TRI, NULL, NULL, 3, {AT(1, 1, 0), AT(1, 0, 0), AT(0, 0, 0)}},
    {"xform_begin.pbrt", "parser.cpp: TransformBegin/End are deprecated and read as AttributeBegin/End",
     "WorldBegin\nTransformBegin\nTranslate 5 0 0\nActiveTransform EndTime\n" TRI "TransformEnd\nTranslate 0 2 0\n" TRI,
     NULL, NULL, 2, {AT(5, 0, 0), AT(0, 2, 0)}},
    /* pbrt-v4 would also let an AttributeEnd close a TransformBegin; batchrt
    ** refuses a block closed by the other kind's End (a mistake in the file:
    ** examples/lib/pbrt.h), which tests/test_pbrt_camera.c pins. */
    /* WorldBegin, named coordinate systems */
    {"world_ctm.pbrt", "fileformat-v4 / scene.cpp WorldBegin: the CTM is reset to the identity (the camera's "
     "transforms do not move shapes)",
     "LookAt 0 0 -5  0 0 0  0 1 0\nCamera \"perspective\"\nTranslate 7 7 7\nWorldBegin\n" TRI, NULL, NULL,
     1, {AT(0, 0, 0)}},
    {"world_active.pbrt", "scene.cpp WorldBegin: activeTransformBits = AllTransformsBits",
     "ActiveTransform EndTime\nWorldBegin\nTranslate 1 0 0\n" TRI, NULL, NULL, 1, {AT(1, 0, 0)}},
    {"coord_world.pbrt", "fileformat-v4: WorldBegin names the coordinate system \"world\"",
     "WorldBegin\nTranslate 3 0 0\nCoordSysTransform \"world\"\n" TRI, NULL, NULL, 1, {AT(0, 0, 0)}},
    {"coord_camera.pbrt", "scene.cpp Camera: \"camera\" = Inverse(CTM at Camera) = world from camera; "
     "CTM = Rotate 90 about y, then T(0,0,5): world from camera = T(0,0,-5) R^-1",
     "Rotate 90 0 1 0\nTranslate 0 0 5\nCamera \"perspective\"\nWorldBegin\nCoordSysTransform \"camera\"\n" TRI,
     NULL, NULL, 1, {{0, 0, -5, 0, 0, -4, 0, 1, -5}}},
    {"coord_ortho.pbrt", "scene.cpp Camera: any camera, not only \"perspective\", names \"camera\"",
     "Translate 0 0 5\nCamera \"orthographic\"\nWorldBegin\nCoordSysTransform \"camera\"\n" TRI, NULL, NULL,
     1, {AT(0, 0, -5)}},
    {"no_world.pbrt", "pbrt.h: a file without WorldBegin (a geometry file opened on its own) is all world, "
     "under its CTM", "Translate 1 0 0\n" TRI, NULL, NULL, 1, {AT(1, 0, 0)}},
    {"coord_global.pbrt", "scene.cpp: namedCoordinateSystems is the builder's, not the graphics state's: a "
     "name defined inside a block outlives AttributeEnd",
     "WorldBegin\nAttributeBegin\nTranslate 3 0 0\nCoordinateSystem \"a\"\nAttributeEnd\nTranslate 0 9 0\n"
     "CoordSysTransform \"a\"\n" TRI, NULL, NULL, 1, {AT(3, 0, 0)}},
    {"coord_redefine.pbrt", "scene.cpp CoordinateSystem: namedCoordinateSystems[name] = ctm: a second "
     "definition replaces the first",
     "WorldBegin\nTranslate 1 0 0\nCoordinateSystem \"a\"\nTranslate 1 0 0\nCoordinateSystem \"a\"\nIdentity\n"
     "CoordSysTransform \"a\"\n" TRI, NULL, NULL, 1, {AT(2, 0, 0)}},
    {"coord_copy.pbrt", "CoordinateSystem records the CTM's value: later transforms do not change it",
     "WorldBegin\nCoordinateSystem \"a\"\nTranslate 5 0 0\nCoordSysTransform \"a\"\nTranslate 0 1 0\n" TRI,
     NULL, NULL, 1, {AT(0, 1, 0)}},
    {"coord_active.pbrt", "scene.cpp CoordSysTransform: graphicsState.ctm = the named set, whatever "
     "ActiveTransform says (it is not one of the ForActiveTransforms directives)",
     "WorldBegin\nTranslate 4 0 0\nCoordinateSystem \"a\"\nIdentity\nActiveTransform EndTime\n"
     "CoordSysTransform \"a\"\n" TRI, NULL, NULL, 1, {AT(4, 0, 0)}},
    {"coord_unknown.pbrt", "scene.cpp CoordSysTransform: an unknown name is a warning; the CTM stays",
     "WorldBegin\nTranslate 2 0 0\nCoordSysTransform \"nowhere\"\n" TRI, NULL, NULL, 1, {AT(2, 0, 0)}},
    /* ActiveTransform: every transform directive goes through ForActiveTransforms */
    {"active_simple.pbrt", "fileformat-v4 'Transformations': under ActiveTransform EndTime, Translate, Scale, "
     "Rotate and LookAt change the end transform only (pbrt.h: only the start one is kept)",
     "WorldBegin\nTranslate 1 0 0\nActiveTransform EndTime\nTranslate 9 0 0\nScale 2 2 2\nRotate 90 0 0 1\n"
     "LookAt 1 2 3  4 5 6  0 1 0\nActiveTransform All\n" TRI, NULL, NULL, 1, {AT(1, 0, 0)}},
    {"active_transform.pbrt", "scene.cpp Transform: ForActiveTransforms: EndTime leaves the start CTM",
     "WorldBegin\nTranslate 1 0 0\nActiveTransform EndTime\nTransform [1 0 0 0  0 1 0 0  0 0 1 0  7 7 7 1]\n"
     "ActiveTransform All\n" TRI, NULL, NULL, 1, {AT(1, 0, 0)}},
    {"active_concat.pbrt", "scene.cpp ConcatTransform: ForActiveTransforms",
     "WorldBegin\nTranslate 1 0 0\nActiveTransform EndTime\nConcatTransform [1 0 0 0  0 1 0 0  0 0 1 0  7 7 7 1]\n"
     "ActiveTransform All\n" TRI, NULL, NULL, 1, {AT(1, 0, 0)}},
    {"active_identity.pbrt", "scene.cpp Identity: ForActiveTransforms",
     "WorldBegin\nTranslate 1 0 0\nActiveTransform EndTime\nIdentity\nActiveTransform All\n" TRI, NULL, NULL,
     1, {AT(1, 0, 0)}},
    {"active_start.pbrt", "fileformat-v4: ActiveTransform StartTime: transforms change the start transform",
     "WorldBegin\nActiveTransform EndTime\nActiveTransform StartTime\nTranslate 1 0 0\n" TRI, NULL, NULL,
     1, {AT(1, 0, 0)}},
    {"active_instance.pbrt", "scene.cpp ObjectInstance: RenderFromObject(0), the start CTM",
     "WorldBegin\nObjectBegin \"a\"\n" TRI "ObjectEnd\nTranslate 1 0 0\nActiveTransform EndTime\nTranslate 5 0 0\n"
     "ObjectInstance \"a\"\n", NULL, NULL, 1, {AT(1, 0, 0)}},
    /* every transform directive, one form each */
    {"translate.pbrt", "fileformat-v4: Translate x y z", "WorldBegin\nTranslate 1 2 3\n" TRI, NULL, NULL,
     1, {AT(1, 2, 3)}},
    {"scale.pbrt", "fileformat-v4: Scale x y z", "WorldBegin\nScale 2 3 4\n"
     "Shape \"trianglemesh\" \"point3 P\" [1 1 1  1 0 0  0 0 1]\n", NULL, NULL, 1, {{2, 3, 4, 2, 0, 0, 0, 0, 4}}},
    {"rotate_y.pbrt", "fileformat-v4: Rotate angle x y z, degrees, right-handed: 90 about y takes x to -z, "
     "z to x", "WorldBegin\nRotate 90 0 1 0\nShape \"trianglemesh\" \"point3 P\" [1 0 0  0 0 1  0 1 0]\n",
     NULL, NULL, 1, {{0, 0, -1, 1, 0, 0, 0, 1, 0}}},
    {"rotate_neg.pbrt", "Rotate -90 about z takes x to -y, y to x", "WorldBegin\nRotate -90 0 0 1\n" TRI,
     NULL, NULL, 1, {{0, 0, 0, 0, -1, 0, 1, 0, 0}}},
    {"rotate_axis.pbrt", "Rotate 120 about (1,1,1) cycles the axes: x to y, y to z",
     "WorldBegin\nRotate 120 1 1 1\n" TRI, NULL, NULL, 1, {{0, 0, 0, 0, 1, 0, 0, 0, 1}}},
    {"lookat.pbrt", "fileformat-v4: LookAt is camera from world (the inverse of right, up, dir, eye); eye "
     "(1,2,3) looking along +x with up +y: right = up x dir = (0,0,-1), so world p -> "
     "(right.(p-e), up.(p-e), dir.(p-e))",
     "WorldBegin\nLookAt 1 2 3  2 2 3  0 1 0\nShape \"trianglemesh\" \"point3 P\" [2 2 3  1 2 4  1 3 3]\n",
     NULL, NULL, 1, {{0, 0, 1, -1, 0, 0, 0, 1, 0}}},
    {"concat_order.pbrt", "scene.cpp ConcatTransform: ctm = ctm * M: M acts first (M: 90 about z, "
     "column by column)", "WorldBegin\nTranslate 1 0 0\nConcatTransform [0 1 0 0  -1 0 0 0  0 0 1 0  0 0 0 1]\n"
     TRI, NULL, NULL, 1, {{1, 0, 0, 1, 1, 0, 0, 0, 0}}},
    {"transform_replace.pbrt", "scene.cpp Transform: the CTM becomes the matrix (not multiplied)",
     "WorldBegin\nRotate 90 0 0 1\nTransform [1 0 0 0  0 1 0 0  0 0 1 0  0 0 6 1]\n" TRI, NULL, NULL,
     1, {AT(0, 0, 6)}},
    {"reverse.pbrt", "fileformat-v4: ReverseOrientation flips normals only: the vertices stay in order",
     "WorldBegin\nReverseOrientation\n" TRI "AttributeBegin\nReverseOrientation\nAttributeEnd\n" TRI, NULL, NULL,
     2, {AT(0, 0, 0), AT(0, 0, 0)}},
    /* ObjectBegin / ObjectEnd / ObjectInstance */
    {"obj_ctm.pbrt", "scene.cpp ObjectBegin pushes the graphics state, ObjectEnd pops it: a Translate inside "
     "the definition moves its shapes, not what follows",
     "WorldBegin\nObjectBegin \"a\"\nTranslate 5 0 0\n" TRI "ObjectEnd\n" TRI "ObjectInstance \"a\"\n", NULL, NULL,
     2, {AT(0, 0, 0), AT(5, 0, 0)}},
    {"obj_active.pbrt", "scene.cpp ObjectEnd restores activeTransformBits as AttributeEnd does",
     "WorldBegin\nObjectBegin \"a\"\nActiveTransform EndTime\nObjectEnd\nTranslate 1 0 0\n" TRI, NULL, NULL,
     1, {AT(1, 0, 0)}},
    {"obj_order.pbrt", "scene.cpp ObjectInstance: world = CTM(instance) * CTM(shape): Rotate 90 z at the "
     "instance, Translate 1 0 0 at the shape: the origin goes to R (1,0,0) = (0,1,0)",
     "WorldBegin\nObjectBegin \"a\"\nTranslate 1 0 0\n" TRI "ObjectEnd\nRotate 90 0 0 1\nObjectInstance \"a\"\n",
     NULL, NULL, 1, {{0, 1, 0, 0, 2, 0, -1, 1, 0}}},
    {"obj_prior.pbrt", "pbrt.h: a shape in an object is baked with the full CTM, the one before ObjectBegin "
     "included", "WorldBegin\nTranslate 0 0 2\nObjectBegin \"a\"\n" TRI "ObjectEnd\nIdentity\n"
     "ObjectInstance \"a\"\n", NULL, NULL, 1, {AT(0, 0, 2)}},
    {"obj_attr.pbrt", "an ObjectInstance inside a block takes the block's CTM; after AttributeEnd the outer one",
     "WorldBegin\nObjectBegin \"a\"\n" TRI "ObjectEnd\nAttributeBegin\nTranslate 2 0 0\nObjectInstance \"a\"\n"
     "AttributeEnd\nObjectInstance \"a\"\n", NULL, NULL, 2, {AT(2, 0, 0), AT(0, 0, 0)}},
    {"obj_coordsys.pbrt", "CoordSysTransform inside a definition sets the shapes' CTM",
     "WorldBegin\nTranslate 3 0 0\nCoordinateSystem \"c\"\nIdentity\nObjectBegin \"a\"\nCoordSysTransform \"c\"\n"
     TRI "ObjectEnd\nObjectInstance \"a\"\n", NULL, NULL, 1, {AT(3, 0, 0)}},
    /* Include (textual) and Import (a copy of the state) */
    {"inc_leak.pbrt", "parser.cpp Include: the file's tokens are read in place (fileStack): its Translate "
     "goes on in force after it", "WorldBegin\nInclude \"inc_leak_t.pbrt\"\n" TRI,
     "inc_leak_t.pbrt", "Translate 1 0 0\n", 1, {AT(1, 0, 0)}},
    {"inc_block.pbrt", "Include is textual: a block opened in the included file closes in the main file",
     "WorldBegin\nInclude \"inc_block_t.pbrt\"\n" TRI "AttributeEnd\n" TRI,
     "inc_block_t.pbrt", "AttributeBegin\nTranslate 1 0 0\n", 2, {AT(1, 0, 0), AT(0, 0, 0)}},
    {"inc_close.pbrt", "Include is textual: a block opened in the main file closes in the included file "
     "(an Import's could not: e_imp_end)",
     "WorldBegin\nAttributeBegin\nTranslate 1 0 0\nInclude \"inc_close_t.pbrt\"\n" TRI,
     "inc_close_t.pbrt", TRI "AttributeEnd\n", 2, {AT(1, 0, 0), AT(0, 0, 0)}},
    {"inc_attr.pbrt", "an Include inside a block: AttributeEnd undoes the included Translate",
     "WorldBegin\nAttributeBegin\nInclude \"inc_attr_t.pbrt\"\nAttributeEnd\n" TRI,
     "inc_attr_t.pbrt", "Translate 1 0 0\n", 1, {AT(0, 0, 0)}},
    {"obj_include.pbrt", "an Include inside ObjectBegin: its shapes are the object's, its Translate ends "
     "at ObjectEnd", "WorldBegin\nObjectBegin \"a\"\nInclude \"obj_include_t.pbrt\"\nObjectEnd\n" TRI
     "ObjectInstance \"a\"\n", "obj_include_t.pbrt", "Translate 0 1 0\n" TRI, 2, {AT(0, 0, 0), AT(0, 1, 0)}},
    {"obj_import.pbrt", "scene.cpp CopyForImport: an Import inside ObjectBegin adds to the object being defined",
     "WorldBegin\nObjectBegin \"a\"\nImport \"obj_import_t.pbrt\"\n" TRI "ObjectEnd\nTranslate 5 0 0\n"
     "ObjectInstance \"a\"\n", "obj_import_t.pbrt", "Translate 0 1 0\n" TRI, 2, {AT(5, 1, 0), AT(5, 0, 0)}},
    {"inc_twice.pbrt", "the same file included twice is no cycle: read twice, textually (two Translates)",
     "WorldBegin\nInclude \"inc_twice_t.pbrt\"\nInclude \"inc_twice_t.pbrt\"\n", "inc_twice_t.pbrt",
     "Translate 1 0 0\n" TRI, 2, {AT(1, 0, 0), AT(2, 0, 0)}},
    {"imp_inherit.pbrt", "scene.cpp CopyForImport: the imported file starts with the importer's graphics state",
     "WorldBegin\nTranslate 2 0 0\nImport \"imp_inherit_t.pbrt\"\n", "imp_inherit_t.pbrt", TRI,
     1, {AT(2, 0, 0)}},
    {"imp_noleak.pbrt", "parser.cpp Import: parsed by a copy of the builder (CopyForImport), merged back "
     "shapes only (MergeImported): its Translate does not reach the main file",
     "WorldBegin\nImport \"imp_noleak_t.pbrt\"\n" TRI, "imp_noleak_t.pbrt", "Translate 1 0 0\n" TRI,
     2, {AT(1, 0, 0), AT(0, 0, 0)}},
    {"imp_active.pbrt", "Import: an ActiveTransform in the imported file stays there",
     "WorldBegin\nImport \"imp_active_t.pbrt\"\nTranslate 1 0 0\n" TRI, "imp_active_t.pbrt",
     "ActiveTransform EndTime\n", 1, {AT(1, 0, 0)}},
    {"imp_object.pbrt", "Import: objects defined in the imported file are merged (MergeImported); the "
     "instance is T(0,3,0) of the main file times the definition's T(1,0,0)",
     "WorldBegin\nImport \"imp_object_t.pbrt\"\nTranslate 0 3 0\nObjectInstance \"o\"\n", "imp_object_t.pbrt",
     "Translate 1 0 0\nObjectBegin \"o\"\n" TRI "ObjectEnd\n", 1, {AT(1, 3, 0)}},
};

/* Each case of the table: the triangles placed where the rule puts them. */
static void test_state_table(void)
{
    size_t i;
    for (i = 0; i < sizeof state_cases / sizeof *state_cases; i++) {
        const state_case *k = &state_cases[i];
        ex_pbrt *s;
        brt_error err;
        double *c = NULL;
        long n;
        int t, j, bad = 0;
        if (k->inc_name) tu_put(k->inc_name, k->inc_text);
        if (ex_pbrt_open(tu_put(k->name, k->text), &s, &err) != BRT_OK) {
            test_fail_at(__FILE__, __LINE__, "%s (%s): %s", k->name, k->rule, err.message);
            continue;
        }
        n = placed(s, &c);
        ex_pbrt_close(s);
        if (n < 0) continue;
        if (n != k->count) {
            test_fail_at(__FILE__, __LINE__, "%s: %ld triangles, expected %d\n  rule: %s", k->name, n, k->count, k->rule);
            free(c);
            continue;
        }
        for (t = 0; t < k->count && !bad; t++)
            for (j = 0; j < 9; j++)
                if (fabs(c[9 * t + j] - k->want[t][j]) > 1e-5) {
                    test_fail_at(__FILE__, __LINE__, "%s: triangle %d is (%g,%g,%g) (%g,%g,%g) (%g,%g,%g), expected "
                                 "(%g,%g,%g) (%g,%g,%g) (%g,%g,%g)\n  rule: %s", k->name, t, c[9 * t], c[9 * t + 1],
                                 c[9 * t + 2], c[9 * t + 3], c[9 * t + 4], c[9 * t + 5], c[9 * t + 6], c[9 * t + 7],
                                 c[9 * t + 8], k->want[t][0], k->want[t][1], k->want[t][2], k->want[t][3],
                                 k->want[t][4], k->want[t][5], k->want[t][6], k->want[t][7], k->want[t][8], k->rule);
                    bad = 1;
                    break;
                }
        free(c);
    }
}

/* ---- 2. where errors point: a table ---------------------------------- */

typedef struct error_case {
    const char *name;
    const char *why;        /* the property the case pins */
    const char *text;
    const char *inc_name;   /* a second file, or NULL */
    const char *inc_text;
    brt_result result;
    const char *want;       /* "file:line: message" (the file's name after the scratch folder) */
} error_case;

static const error_case error_cases[] = {
    {"e_twice.pbrt", "the same mistake twice: the first is reported",
     "WorldBegin\nFrob 1\nTranslate 1 0 0\nFrob 2\n", NULL, NULL, BRT_EPARSE, "e_twice.pbrt:2: unknown directive 'Frob'"},
    {"e_after_p.pbrt", "lines inside a multi-line P (the fast path's own line counter) are counted",
     "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [\n0 0 0\n1 0 0\n0 1 0\n]\nFrob\n", NULL, NULL, BRT_EPARSE,
     "e_after_p.pbrt:7: unknown directive 'Frob'"},
    {"e_after_idx.pbrt", "lines inside multi-line indices are counted",
     "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0] \"integer indices\" [\n0 1 2\n\n"
     "2 1 0\n]\nFrob\n", NULL, NULL, BRT_EPARSE, "e_after_idx.pbrt:7: unknown directive 'Frob'"},
    {"e_comments.pbrt", "comments (with a quote) and CRLF line ends count their lines",
     "WorldBegin\r\n# a \"comment\r\n\r\n  # another\nFrob\r\n", NULL, NULL, BRT_EPARSE,
     "e_comments.pbrt:5: unknown directive 'Frob'"},
    {"e_skipped.pbrt", "lines inside a skipped directive's parameter lists are counted",
     "WorldBegin\nMaterial \"diffuse\" \"rgb reflectance\" [\n.5\n.5\n.5 ]\nFrob\n", NULL, NULL, BRT_EPARSE,
     "e_skipped.pbrt:6: unknown directive 'Frob'"},
    {"e_in_inc.pbrt", "an error in an included file names that file and its line",
     "WorldBegin\n\n\nInclude \"e_inc/x.pbrt\"\n", "e_inc/x.pbrt", "Translate 1 0 0\n\nFrob\n", BRT_EPARSE,
     "e_inc/x.pbrt:3: unknown directive 'Frob'"},
    {"e_after_inc.pbrt", "after an Include returns, lines are the main file's again",
     "WorldBegin\nInclude \"e_inc/ten.pbrt\"\nTranslate 1 0 0\nFrob\n", "e_inc/ten.pbrt",
     "\n\n\n\n\n\n\n\n\nTranslate 0 1 0\n", BRT_EPARSE, "e_after_inc.pbrt:4: unknown directive 'Frob'"},
    {"e_after_imp.pbrt", "after an Import returns, lines are the main file's again",
     "WorldBegin\nImport \"e_inc/ten2.pbrt\"\n\nFrob\n", "e_inc/ten2.pbrt",
     "\n\n\n\n\n\n\n\n\n" TRI, BRT_EPARSE, "e_after_imp.pbrt:4: unknown directive 'Frob'"},
    {"e_open_inc.pbrt", "an AttributeBegin never closed is named where it is, in the included file",
     "WorldBegin\nInclude \"e_inc/open.pbrt\"\n" TRI, "e_inc/open.pbrt", "\nAttributeBegin\n", BRT_EPARSE,
     "e_inc/open.pbrt:2: AttributeBegin never closed"},
    {"e_obj_open.pbrt", "an ObjectBegin never closed is named as one",
     "WorldBegin\nAttributeBegin\nAttributeEnd\nObjectBegin \"a\"\n" TRI, NULL, NULL, BRT_EPARSE,
     "e_obj_open.pbrt:4: ObjectBegin never closed"},
    {"e_nested_inc.pbrt", "an Include inside an Include: after the inner one returns, lines are the outer "
     "included file's", "WorldBegin\nInclude \"e_inc/outer.pbrt\"\n", "e_inc/outer.pbrt",
     "\nInclude \"e_inc/blank4.pbrt\"\n\nFrob\n", BRT_EPARSE, "e_inc/outer.pbrt:4: unknown directive 'Frob'"},
    {"e_open_inner.pbrt", "of nested blocks never closed, the innermost is named",
     "WorldBegin\nAttributeBegin\nAttributeBegin\nAttributeEnd\nAttributeBegin\n", NULL, NULL, BRT_EPARSE,
     "e_open_inner.pbrt:5: AttributeBegin never closed"},
    {"e_unknown_twice.pbrt", "ObjectInstance of an unknown object used twice: the first use is named",
     "WorldBegin\nObjectInstance \"t\"\n\nObjectInstance \"t\"\n", NULL, NULL, BRT_EPARSE,
     "e_unknown_twice.pbrt:2: ObjectInstance of unknown object \"t\""},
    {"e_unknown_inc.pbrt", "ObjectInstance of an unknown object in an included file names that file",
     "WorldBegin\nInclude \"e_inc/use.pbrt\"\nObjectInstance \"t\"\n", "e_inc/use.pbrt", "\n\nObjectInstance \"t\"\n",
     BRT_EPARSE, "e_inc/use.pbrt:3: ObjectInstance of unknown object \"t\""},
    {"e_index_twice.pbrt", "an out-of-range index on two lines: the first place is named",
     "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n\"integer indices\" [0 1 2\n0 1 5\n"
     "# a comment: the slow path\n5 1 0]\n", NULL, NULL, BRT_EPARSE,
     "e_index_twice.pbrt:4: Shape \"trianglemesh\": index 5 out of range (3 vertices)"},
    {"e_index_late.pbrt", "the largest index is named on its line, past a comment",
     "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n\"integer indices\" [0 1 2\n0 1 2\n"
     "# a comment: the slow path\n7 1 0]\n", NULL, NULL, BRT_EPARSE,
     "e_index_late.pbrt:6: Shape \"trianglemesh\": index 7 out of range (3 vertices)"},
    {"e_mixed_inc.pbrt", "an AttributeEnd closing an ObjectBegin names the ObjectBegin's file and line",
     "WorldBegin\nInclude \"e_inc/obj.pbrt\"\nAttributeEnd\n", "e_inc/obj.pbrt", "\n\nObjectBegin \"a\"\n",
     BRT_EPARSE, "e_mixed_inc.pbrt:3: AttributeEnd while the ObjectBegin at "},
    {"e_mixed_inc2.pbrt", "... and the ObjectBegin's place in that message is the included file's line",
     "WorldBegin\nInclude \"e_inc/obj2.pbrt\"\nAttributeEnd\n", "e_inc/obj2.pbrt", "\n\n\nObjectBegin \"a\"\n",
     BRT_EPARSE, "e_inc/obj2.pbrt:4 is open"},   /* line 4: not the AttributeEnd's line 3 */
    {"e_imp_open.pbrt", "pbrt-v4 MergeImported: an AttributeBegin not closed in an imported file is an error",
     "WorldBegin\nAttributeBegin\nImport \"e_inc/impopen.pbrt\"\nAttributeEnd\n", "e_inc/impopen.pbrt",
     "AttributeBegin\n", BRT_EPARSE, "e_inc/impopen.pbrt:1: AttributeBegin never closed"},
    {"e_imp_end.pbrt", "pbrt-v4 Import: the imported file's builder has no pushed state: its AttributeEnd "
     "cannot close the importer's AttributeBegin",
     "WorldBegin\nAttributeBegin\nImport \"e_inc/impend.pbrt\"\nAttributeEnd\n", "e_inc/impend.pbrt",
     "\nAttributeEnd\n", BRT_EPARSE, "e_inc/impend.pbrt:2: AttributeEnd without AttributeBegin"},
    {"e_imp_inc_end.pbrt", "an Include inside an Import belongs to the Import: its AttributeEnd cannot close "
     "the importer's AttributeBegin either",
     "WorldBegin\nAttributeBegin\nImport \"e_inc/impinc.pbrt\"\nAttributeEnd\n", "e_inc/impinc.pbrt",
     "Include \"e_inc/impinc_end.pbrt\"\n", BRT_EPARSE, "e_inc/impinc_end.pbrt:2: AttributeEnd without AttributeBegin"},
    {"e_objend_imp.pbrt", "scene.cpp ObjectEnd: \"ObjectEnd called inside Import for instance definition\" "
     "is an error", "WorldBegin\nObjectBegin \"a\"\nImport \"e_inc/objend.pbrt\"\nObjectEnd\n", "e_inc/objend.pbrt",
     "\nObjectEnd\n", BRT_EPARSE, "e_inc/objend.pbrt:2: ObjectEnd without ObjectBegin"},
    /* documented limits: exactly at them and one step past */
    {"e_vector_p.pbrt", "fileformat-v4: P is a \"point3\" parameter; a \"vector3 P\" is not the positions",
     "WorldBegin\nShape \"trianglemesh\" \"vector3 P\" [0 0 0 1 0 0 0 1 0]\n", NULL, NULL, BRT_EPARSE,
     "e_vector_p.pbrt:2: Shape \"trianglemesh\" without \"point3 P\""},
    {"e_tri_noidx.pbrt", "trianglemesh: only exactly 3 points may go without indices (6 may not)",
     "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0 0 0 1 1 0 1 0 1 1]\n", NULL, NULL,
     BRT_EPARSE, "e_tri_noidx.pbrt:2: Shape \"trianglemesh\": \"indices\" missing"},
    {"e_bil_3.pbrt", "bilinearmesh: only exactly 4 points may go without indices (3 may not)",
     "WorldBegin\nShape \"bilinearmesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n", NULL, NULL,
     BRT_EPARSE, "e_bil_3.pbrt:2: Shape \"bilinearmesh\": \"indices\" missing"},
    {"e_bil_8.pbrt", "bilinearmesh: ... nor 8",
     "WorldBegin\nShape \"bilinearmesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0 1 1 0 0 0 1 1 0 1 0 1 1 1 1 1]\n", NULL,
     NULL, BRT_EPARSE, "e_bil_8.pbrt:2: Shape \"bilinearmesh\": \"indices\" missing"},
    {"e_bil_range.pbrt", "bilinearmesh: an index equal to the vertex count is out of range",
     "WorldBegin\nShape \"bilinearmesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0 1 1 0] \"integer indices\" [0 1 2 4]\n",
     NULL, NULL, BRT_EPARSE, "e_bil_range.pbrt:2: Shape \"bilinearmesh\": index 4 out of range (4 vertices)"},
    {"e_affine4.pbrt", "Transform: number 4 (row 4, column 1) must be 0",
     "WorldBegin\nTransform [1 0 0 1  0 1 0 0  0 0 1 0  0 0 0 1]\n", NULL, NULL, BRT_EPARSE, "e_affine4.pbrt:2: only affine"},
    {"e_affine8.pbrt", "ConcatTransform: number 8 must be 0",
     "WorldBegin\nConcatTransform [1 0 0 0  0 1 0 1  0 0 1 0  0 0 0 1]\n", NULL, NULL, BRT_EPARSE,
     "e_affine8.pbrt:2: only affine"},
    {"e_affine12.pbrt", "Transform: number 12 must be 0",
     "WorldBegin\nTransform [1 0 0 0  0 1 0 0  0 0 1 1  0 0 0 1]\n", NULL, NULL, BRT_EPARSE, "e_affine12.pbrt:2: only affine"},
    {"e_affine16.pbrt", "Transform: number 16 must be 1 (2 is a projective scale)",
     "WorldBegin\nTransform [1 0 0 0  0 1 0 0  0 0 1 0  0 0 0 2]\n", NULL, NULL, BRT_EPARSE, "e_affine16.pbrt:2: only affine"},
    {"e_active.pbrt", "ActiveTransform takes All, StartTime or EndTime only",
     "WorldBegin\nActiveTransform Middle\n", NULL, NULL, BRT_EPARSE, "e_active.pbrt:2: ActiveTransform: expected"},
};

static void test_error_table(void)
{
    size_t i;
    for (i = 0; i < sizeof error_cases / sizeof *error_cases; i++) {
        const error_case *k = &error_cases[i];
        if (k->inc_name) tu_put(k->inc_name, k->inc_text);
        tu_put("e_inc/impinc_end.pbrt", "\nAttributeEnd\n");
        tu_put("e_inc/blank4.pbrt", "\n\n\n\nTranslate 0 0 1\n");
        expect_error(k->name, k->text, k->result, k->want);
        if (test_failed()) { test_fail_at(__FILE__, __LINE__, "(%s: %s)", k->name, k->why); return; }
    }
}

/* ---- 4. thresholds: 65,536 instances and triangles per chunk ---------- */

/* n instances of one object, the i-th (from 0) at Translate (i+1) 0 0
** (each line adds 1 to the CTM), followed by tail. */
static char *many_instances(uint32_t n, const char *tail)
{
    size_t cap = (size_t)n * 40 + 256, len = 0;
    char *text = malloc(cap);
    uint32_t i;
    if (!text) return NULL;
    len += (size_t)snprintf(text, cap, "WorldBegin\nObjectBegin \"a\"\n" TRI "ObjectEnd\n");
    for (i = 0; i < n; i++) len += (size_t)snprintf(text + len, cap - len, "Translate 1 0 0\nObjectInstance \"a\"\n");
    snprintf(text + len, cap - len, "%s", tail);
    return text;
}

/* pbrt.h: "instances in file order"; the instance stream hands them on in
** chunks numbered by their first instance.  Across the chunk size (65,536)
** and past it, every instance keeps its number and its own transform: a
** chunk numbered by chunk, or a lost or repeated instance at the seam,
** fails here (test scenes have at most 1,725 instances, so nothing else
** reaches the second chunk).  The 70,000-instance file (2.4 MB, past the
** 1 MiB window) also pins the line count of an error at its end. */
static void test_instance_chunks(void)
{
    static const uint32_t sizes[] = {65535, 65536, 65537, 70000};
    size_t z;
    for (z = 0; z < sizeof sizes / sizeof *sizes; z++) {
        uint32_t n = sizes[z], i, bad = 0, count = 0;
        char name[64], *text = many_instances(n, "");
        brt_scene_source src;
        brt_error err;
        ex_pbrt *s;
        insts in;
        CHECK(text, "out of memory");
        snprintf(name, sizeof name, "inst_%u.pbrt", (unsigned)n);
        tu_put(name, text);
        free(text);
        if (ex_pbrt_open(tu_scratch(name), &s, &err) != BRT_OK) { EXPECT(0, "%s: %s", name, err.message); continue; }
        ex_pbrt_counts(s, NULL, NULL, &count);
        EXPECT(count == n, "%s: %u instances counted", name, (unsigned)count);
        memset(&in, 0, sizeof in);
        ex_pbrt_source(s, &src);
        if (src.instances(src.user, collect_inst, &in, &err) != BRT_OK) EXPECT(0, "%s: %s", name, err.message);
        EXPECT(in.n == n && !in.bad_first, "%s: %u instances streamed (chunks numbered right: %d)", name,
               (unsigned)in.n, !in.bad_first);
        EXPECT(in.chunks == (n + 65535) / 65536 && in.max_chunk <= 65536, "%s: %u chunks, the largest %u", name,
               (unsigned)in.chunks, (unsigned)in.max_chunk);
        for (i = 0; i < in.n && i < n; i++) {
            const float *x = in.v[i].xform;
            if ((in.v[i].prototype != 0 || x[0] != 1 || x[5] != 1 || x[10] != 1 || x[3] != (float)(i + 1) || x[7] != 0
                 || x[11] != 0) && bad++ < 3)
                EXPECT(0, "%s: instance %u: prototype %u, translation (%g,%g,%g), expected (%u,0,0)", name, (unsigned)i,
                       (unsigned)in.v[i].prototype, x[3], x[7], x[11], (unsigned)(i + 1));
        }
        free(in.v);
        ex_pbrt_close(s);
    }
    {
        /* 4 lines, 2 * 70000, a blank one, then the error: line 140006 */
        char *text = many_instances(70000, "\nFrob\n");
        CHECK(text, "out of memory");
        expect_error("inst_err.pbrt", text, BRT_EPARSE, "inst_err.pbrt:140006: unknown directive 'Frob'");
        free(text);
    }
}

/* n triangles (k, k+1, k+2) over vertices (k, k % 2, 0), in the world or
** in an object instanced once. */
static char *many_triangles(uint32_t n, int object)
{
    size_t cap = (size_t)n * 40 + 256, len = 0;
    char *text = malloc(cap);
    uint32_t k;
    if (!text) return NULL;
    len += (size_t)snprintf(text, cap, "WorldBegin\n%sShape \"trianglemesh\" \"point3 P\" [", object ? "ObjectBegin \"m\"\n" : "");
    for (k = 0; k < n + 2; k++) len += (size_t)snprintf(text + len, cap - len, "%u %u 0\n", (unsigned)k, (unsigned)(k % 2));
    len += (size_t)snprintf(text + len, cap - len, "] \"integer indices\" [");
    for (k = 0; k < n; k++)
        len += (size_t)snprintf(text + len, cap - len, "%u %u %u\n", (unsigned)k, (unsigned)k + 1, (unsigned)k + 2);
    snprintf(text + len, cap - len, "]\n%s", object ? "ObjectEnd\nObjectInstance \"m\"\n" : "");
    return text;
}

/* pbrt.h: "one chunk of 65536 triangles"; batchrt.h's triangle stream
** numbers each chunk by its first triangle.  65,535 and 65,536 triangles
** are one chunk (no empty chunk after a full one), 65,537 two; every
** triangle in order, in the world stream and in a prototype's. */
static void test_triangle_chunks(void)
{
    static const uint32_t sizes[] = {65535, 65536, 65537};
    size_t z;
    int object;
    for (object = 0; object < 2; object++)
        for (z = 0; z < sizeof sizes / sizeof *sizes; z++) {
            uint32_t n = sizes[z], k, bad = 0;
            char name[64], *text = many_triangles(n, object);
            brt_scene_source src;
            brt_error err;
            ex_pbrt *s;
            tris t;
            brt_result r;
            CHECK(text, "out of memory");
            snprintf(name, sizeof name, "tris_%u_%d.pbrt", (unsigned)n, object);
            tu_put(name, text);
            free(text);
            if (ex_pbrt_open(tu_scratch(name), &s, &err) != BRT_OK) { EXPECT(0, "%s: %s", name, err.message); continue; }
            memset(&t, 0, sizeof t);
            ex_pbrt_source(s, &src);
            r = object ? src.prototype(src.user, 0, collect, &t, &err) : src.world.run(src.world.user, collect, &t, &err);
            EXPECT(r == BRT_OK, "%s: %s", name, r == BRT_OK ? "" : err.message);
            EXPECT(t.n == n && !t.bad_first, "%s: %u triangles (chunks numbered right: %d)", name, (unsigned)t.n,
                   !t.bad_first);
            EXPECT(t.chunks == (n + 65535) / 65536 && t.max_chunk <= 65536, "%s: %u chunks, the largest %u", name,
                   (unsigned)t.chunks, (unsigned)t.max_chunk);
            for (k = 0; k < t.n && k < n; k++) {
                const float *c = t.c + 9 * (size_t)k;
                if ((c[0] != (float)k || c[1] != (float)(k % 2) || c[3] != (float)(k + 1) || c[6] != (float)(k + 2))
                    && bad++ < 3)
                    EXPECT(0, "%s: triangle %u starts at (%g,%g,%g)", name, (unsigned)k, c[0], c[1], c[2]);
            }
            free(t.c);
            ex_pbrt_close(s);
        }
}

/* ---- 8. variants of shapes and files ---------------------------------- */

static const char *quad_ply =
    "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
    "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
    "0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2\n3 0 2 3\n";

/* pbrt.h: bilinearmesh patch (a,b,c,d) -> (a,b,d), (a,d,c), for every
** patch of an index list, under the CTM; plymesh in an object (a
** prototype) and in an imported file under a subfolder, the file name
** against the main file's folder (fileformat-v4: relative to the scene
** file's directory). */
static void test_shape_variants(void)
{
    static const double bil[4][9] = {
        {10, 0, 0, 11, 0, 0, 11, 1, 0}, {10, 0, 0, 11, 1, 0, 10, 1, 0},     /* patch 0 1 2 3 */
        {11, 1, 0, 11, 0, 0, 10, 0, 0}, {11, 1, 0, 10, 0, 0, 10, 1, 0}};    /* patch 3 1 2 0 */
    ex_pbrt *s;
    brt_error err;
    double *c = NULL;
    long n;
    int t, j;
    s = NULL;
    if (ex_pbrt_open(tu_put("v_bil.pbrt", "WorldBegin\nTranslate 10 0 0\nShape \"bilinearmesh\" \"point3 P\" "
                         "[0 0 0 1 0 0 0 1 0 1 1 0] \"integer indices\" [0 1 2 3  3 1 2 0]\n"), &s, &err) == BRT_OK) {
        n = placed(s, &c);
        EXPECT(n == 4, "bilinearmesh of 2 patches: %ld triangles", n);
        for (t = 0; n == 4 && t < 4; t++)
            for (j = 0; j < 9; j++)
                if (c[9 * t + j] != bil[t][j]) { EXPECT(0, "bilinearmesh: triangle %d corner value %d is %g, expected %g",
                                                        t, j, c[9 * t + j], bil[t][j]); j = 9; t = 4; }
        free(c);
        ex_pbrt_close(s);
    } else EXPECT(0, "v_bil.pbrt: %s", err.message);
    tu_put("v/geo/quad.ply", quad_ply);
    tu_put("v/geo/part.pbrt", "Translate 0 0 4\nShape \"plymesh\" \"string filename\" \"geo/quad.ply\"\n"
                           "ObjectBegin \"q\"\nShape \"plymesh\" \"string filename\" \"geo/quad.ply\"\nObjectEnd\n");
    if (ex_pbrt_open(tu_put("v/main.pbrt", "WorldBegin\nImport \"geo/part.pbrt\"\nTranslate 5 0 0\nObjectInstance \"q\"\n"),
                     &s, &err) == BRT_OK) {
        /* world: the quad at z = 4; the instance: T(5,0,0) * T(0,0,4) */
        static const double want[4][3] = {{0, 0, 4}, {1, 1, 4}, {5, 0, 4}, {6, 1, 4}};   /* corners 0 and 1 of tri 0 and 2 */
        n = placed(s, &c);
        EXPECT(n == 4, "plymesh in an import and in an object: %ld triangles, expected 4", n);
        if (n == 4)
            for (t = 0; t < 4; t++) {
                const double *q = c + 9 * (t < 2 ? 0 : 2) + 3 * (t % 2 ? 2 : 0);
                EXPECT(fabs(q[0] - want[t][0]) < 1e-6 && fabs(q[1] - want[t][1]) < 1e-6 && fabs(q[2] - want[t][2]) < 1e-6,
                       "plymesh: point %d at (%g,%g,%g), expected (%g,%g,%g)", t, q[0], q[1], q[2], want[t][0], want[t][1],
                       want[t][2]);
            }
        free(c);
        ex_pbrt_close(s);
    } else EXPECT(0, "v/main.pbrt: %s", err.message);
}

/* pbrt.h: "The streams report errors the same way": a point that
** overflows the float range through its shape's transform is refused
** when streamed, naming the Shape directive's own file and line -- in an
** included file, and not the line of its "P" when that is another one. */
static void test_stream_error_place(void)
{
    ex_pbrt *s;
    brt_error err;
    brt_scene_source src;
    tris t;
    brt_result r;
    tu_put("se/inc.pbrt", "\n\nScale 1e30 1e30 1e30\nShape \"trianglemesh\"\n\"point3 P\" [0 0 0 1e30 0 0 0 1 0]\n");
    if (ex_pbrt_open(tu_put("se/main.pbrt", "WorldBegin\n" TRI "Include \"inc.pbrt\"\n"), &s, &err) != BRT_OK) {
        EXPECT(0, "se/main.pbrt: %s", err.message);
        return;
    }
    memset(&t, 0, sizeof t);
    ex_pbrt_source(s, &src);
    r = src.world.run(src.world.user, collect, &t, &err);
    EXPECT(r == BRT_EPARSE && strstr(err.message, "se/inc.pbrt:4: Shape: a point is not finite in float"),
           "stream: %s (%s)", brt_result_string(r), r == BRT_OK ? "streamed" : err.message);
    free(t.c);
    ex_pbrt_close(s);
}

/* The second pass reads each value where pass 1 found it, seeking back and
** forth in a file far larger than its 1 MiB window: a trianglemesh of 2 MiB
** of "P" whose "indices" follow to the end of the file (read first, they
** take the reader to the end of the file, then it seeks back), twice over.
** Every triangle must be the one its indices name. */
static void test_values_read_back_and_forth(void)
{
    const uint32_t n = 70000;           /* points: about 2 MiB of text */
    size_t cap = 64 * (size_t)n + 4096, used = 0;
    char *text = malloc(cap);
    ex_pbrt *s = NULL;
    brt_scene_source src;
    brt_error err;
    tris t;
    uint32_t k, round, bad = 0;
    CHECK(text, "out of memory");
    used += (size_t)snprintf(text + used, cap - used, "WorldBegin\nShape \"trianglemesh\" \"point3 P\" [");
    for (k = 0; k < n; k++) used += (size_t)snprintf(text + used, cap - used, " %u 0.5 %u", k, k % 7);
    used += (size_t)snprintf(text + used, cap - used, " ]\n\"integer indices\" [");
    for (k = 0; k + 2 < n; k += 3) used += (size_t)snprintf(text + used, cap - used, " %u %u %u", k + 2, k, k + 1);
    snprintf(text + used, cap - used, " ]\n");
    tu_put("back_and_forth.pbrt", text);
    free(text);
    CHECK(ex_pbrt_open(tu_scratch("back_and_forth.pbrt"), &s, &err) == BRT_OK, "%s", err.message);
    ex_pbrt_source(s, &src);
    for (round = 0; round < 2; round++) {
        memset(&t, 0, sizeof t);
        EXPECT(src.world.run(src.world.user, collect, &t, &err) == BRT_OK, "run %u: %s", round, err.message);
        EXPECT(t.n == n / 3, "run %u: %u triangles, want %u", round, (unsigned)t.n, (unsigned)(n / 3));
        for (k = 0; k < t.n && k < n / 3; k++) {
            const float *c = t.c + 9 * (size_t)k;   /* corners k+2, k, k+1 of triangle k/3: x = the point's number */
            if ((c[0] != (float)(3 * k + 2) || c[3] != (float)(3 * k) || c[6] != (float)(3 * k + 1)) && bad++ < 3)
                test_fail_at(__FILE__, __LINE__, "run %u: triangle %u has x %g %g %g", round, (unsigned)k, c[0], c[3],
                             c[6]);
        }
        free(t.c);
    }
    ex_pbrt_close(s);
}

void suite_pbrt_state(void)
{
    test_run("pbrt state: the graphics-state table (blocks, WorldBegin, coordinate systems, ActiveTransform, "
             "every transform, objects, Include and Import)", test_state_table);
    test_run("pbrt state: where errors point (file:line), and documented limits", test_error_table);
    test_run("pbrt state: 65,535 .. 70,000 instances across the chunk seam", test_instance_chunks);
    test_run("pbrt state: 65,535, 65,536, 65,537 triangles per chunk (world and prototype)", test_triangle_chunks);
    test_run("pbrt state: bilinearmesh patches, plymesh in an object and in an Import", test_shape_variants);
    test_run("pbrt state: a stream error names the Shape's file and line", test_stream_error_place);
    test_run("pbrt state: values read back and forth in a file past the window", test_values_read_back_and_forth);
}
