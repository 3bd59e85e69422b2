/*
** tests/test_loopsubdiv.c -- pbrt-v4's Shape "loopsubdiv" (examples/lib/
** loopsubdiv.c and its reading in examples/lib/pbrt.c) against a reference
** written apart here: Loop's rules (Loop 1987, with pbrt-v4's choices of
** beta and of the boundary rules) in double, over an explicit edge list
** searched linearly, slow and plain.  The reference states pbrt-v4's
** numbering independently: edge vertices numbered after the old ones in
** the order their edges are first met, face (a, b, c) split into
** (a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca).  Besides, closed
** forms (levels 0 of an octahedron and a tetrahedron), properties that
** need no reference (counts, flat meshes stay flat, symmetry, limit points
** that a further level leaves in place), the refusals of non-manifold
** input at file:line, and an end-to-end test: a pbrt file's loopsubdiv
** hits the same triangles as the reference's mesh written out as a
** trianglemesh.
*/
#include "test.h"
#include "util.h"
#include "batchrt.h"
#include "../examples/lib/loopsubdiv.h"
#include "../examples/lib/pbrt.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <stdio.h>

/* ---- the reference ------------------------------------------------------ */

typedef struct ref_mesh {
    double *p;              /* 3 per vertex */
    uint32_t *f;            /* 3 per face */
    uint32_t nv, nf;
} ref_mesh;

/* An edge as first met: ends a, b; its faces' opposite corners (o1 is
** none, UINT32_MAX, on a boundary). */
typedef struct ref_edge { uint32_t a, b, o0, o1, faces; } ref_edge;

static void ref_free(ref_mesh *m)
{
    free(m->p);
    free(m->f);
    memset(m, 0, sizeof *m);
}

static void ref_copy(ref_mesh *m, const double *p, uint32_t nv, const uint32_t *f, uint32_t nf)
{
    m->p = malloc(3 * nv * sizeof *m->p);
    m->f = malloc(3 * nf * sizeof *m->f);
    memcpy(m->p, p, 3 * nv * sizeof *m->p);
    memcpy(m->f, f, 3 * nf * sizeof *m->f);
    m->nv = nv;
    m->nf = nf;
}

/* The edges of m in the order first met (faces in order, corners 0-1,
** 1-2, 2-0), found by linear search. */
static ref_edge *ref_edges(const ref_mesh *m, uint32_t *count)
{
    ref_edge *e = malloc(3 * (size_t)m->nf * sizeof *e);
    uint32_t n = 0, i, k, j;
    for (i = 0; i < m->nf; i++)
        for (k = 0; k < 3; k++) {
            uint32_t a = m->f[3 * i + k], b = m->f[3 * i + (k + 1) % 3], o = m->f[3 * i + (k + 2) % 3];
            for (j = 0; j < n; j++)
                if ((e[j].a == a && e[j].b == b) || (e[j].a == b && e[j].b == a)) break;
            if (j < n) { e[j].o1 = o; e[j].faces++; continue; }
            e[n].a = a; e[n].b = b; e[n].o0 = o; e[n].o1 = UINT32_MAX; e[n].faces = 1;
            n++;
        }
    *count = n;
    return e;
}

/* Per vertex: its neighbours (through the edge list), and the ones along
** boundary edges; Loop's vertex rule with weight w(n) of the one-ring or,
** on a boundary, wb of each boundary neighbour. */
static void ref_vertex_rule(const ref_mesh *m, const ref_edge *e, uint32_t ne, uint32_t v, int limit, double out[3])
{
    double ring[3] = {0, 0, 0}, edge[3] = {0, 0, 0};
    uint32_t n = 0, nb = 0, j;
    int k;
    for (j = 0; j < ne; j++) {
        uint32_t other = e[j].a == v ? e[j].b : e[j].b == v ? e[j].a : UINT32_MAX;
        if (other == UINT32_MAX) continue;
        n++;
        for (k = 0; k < 3; k++) ring[k] += m->p[3 * other + k];
        if (e[j].faces == 1) {
            nb++;
            for (k = 0; k < 3; k++) edge[k] += m->p[3 * other + k];
        }
    }
    if (nb > 0) {   /* boundary: 3/4 and 1/8 each while refining, 3/5 and 1/5 at the limit */
        double wb = limit ? 1.0 / 5 : 1.0 / 8;
        for (k = 0; k < 3; k++) out[k] = (1 - 2 * wb) * m->p[3 * v + k] + wb * edge[k];
    } else {        /* interior: beta, or gamma = 1 / (n + 3 / (8 beta)) at the limit */
        double b = n == 3 ? 3.0 / 16 : 3.0 / (8.0 * n), w = limit ? 1 / (n + 3 / (8 * b)) : b;
        for (k = 0; k < 3; k++) out[k] = (1 - n * w) * m->p[3 * v + k] + w * ring[k];
    }
}

/* One level of Loop's scheme. */
static void ref_level(const ref_mesh *in, ref_mesh *out)
{
    uint32_t ne, i, j;
    ref_edge *e = ref_edges(in, &ne);
    int k;
    out->nv = in->nv + ne;
    out->nf = 4 * in->nf;
    out->p = malloc(3 * (size_t)out->nv * sizeof *out->p);
    out->f = malloc(3 * (size_t)out->nf * sizeof *out->f);
    for (i = 0; i < in->nv; i++) ref_vertex_rule(in, e, ne, i, 0, out->p + 3 * i);
    for (j = 0; j < ne; j++)
        for (k = 0; k < 3; k++) {
            double a = in->p[3 * e[j].a + k], b = in->p[3 * e[j].b + k];
            out->p[3 * (in->nv + j) + k] = e[j].faces == 1 ? (a + b) / 2
                : 3.0 / 8 * (a + b) + 1.0 / 8 * (in->p[3 * e[j].o0 + k] + in->p[3 * e[j].o1 + k]);
        }
    for (i = 0; i < in->nf; i++) {
        uint32_t a = in->f[3 * i], b = in->f[3 * i + 1], c = in->f[3 * i + 2], mid[3];
        uint32_t want[12];
        for (k = 0; k < 3; k++) {
            uint32_t x = in->f[3 * i + k], y = in->f[3 * i + (k + 1) % 3];
            for (j = 0; j < ne; j++)
                if ((e[j].a == x && e[j].b == y) || (e[j].a == y && e[j].b == x)) break;
            mid[k] = in->nv + j;
        }
        /* ab = mid[0], bc = mid[1], ca = mid[2] */
        want[0] = a;      want[1] = mid[0];  want[2] = mid[2];
        want[3] = mid[0]; want[4] = b;       want[5] = mid[1];
        want[6] = mid[2]; want[7] = mid[1];  want[8] = c;
        want[9] = mid[0]; want[10] = mid[1]; want[11] = mid[2];
        memcpy(out->f + 12 * (size_t)i, want, sizeof want);
    }
    free(e);
}

/* levels of Loop's scheme, then every vertex to the limit surface. */
static void ref_subdivide(const double *p, uint32_t nv, const uint32_t *f, uint32_t nf, int levels, ref_mesh *out)
{
    ref_mesh cur, next;
    uint32_t ne, i;
    ref_edge *e;
    int l;
    ref_copy(&cur, p, nv, f, nf);
    for (l = 0; l < levels; l++) {
        ref_level(&cur, &next);
        ref_free(&cur);
        cur = next;
    }
    e = ref_edges(&cur, &ne);
    out->nv = cur.nv;
    out->nf = cur.nf;
    out->f = cur.f;
    out->p = malloc(3 * (size_t)cur.nv * sizeof *out->p);
    for (i = 0; i < cur.nv; i++) ref_vertex_rule(&cur, e, ne, i, 1, out->p + 3 * i);
    free(e);
    free(cur.p);
}

/* ---- the meshes ------------------------------------------------------------ */

static const double tetra_p[] = {1, 1, 1, 1, -1, -1, -1, 1, -1, -1, -1, 1};
static const uint32_t tetra_f[] = {0, 1, 2, 0, 3, 1, 0, 2, 3, 1, 3, 2};
static const double octa_p[] = {1, 0, 0, -1, 0, 0, 0, 1, 0, 0, -1, 0, 0, 0, 1, 0, 0, -1};
static const uint32_t octa_f[] = {0, 2, 4, 2, 1, 4, 1, 3, 4, 3, 0, 4, 2, 0, 5, 1, 2, 5, 3, 1, 5, 0, 3, 5};
static const double one_p[] = {0, 0, 0, 1, 0, 0, 0.25, 0.75, 0};
static const uint32_t one_f[] = {0, 1, 2};
static const double square_p[] = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0};
static const uint32_t square_f[] = {0, 1, 2, 0, 2, 3};

/* The module on a control mesh given in double (exact in float here). */
static int module(const double *p, uint32_t nv, const uint32_t *f, uint32_t nf, int levels, ex_loop_mesh *m)
{
    float pf[64];
    uint32_t i;
    brt_error err;
    for (i = 0; i < 3 * nv; i++) pf[i] = (float)p[i];
    if (ex_loop_subdivide(pf, nv, f, nf, levels, m, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "ex_loop_subdivide: %s", err.message);
        return 0;
    }
    return 1;
}

/* The bound of the float module against the double reference: every rule
** is a weighted mean (non-negative weights summing to 1, each rounded to
** float), so each level and the limit push add a few float roundings of
** the mesh's size (coordinates at most 1 here). */
static double bound(int levels)
{
    return 4 * FLT_EPSILON * (levels + 1);
}

/* Module and reference agree: counts, every triangle's corners in order
** (so the numbering of triangles and of their corners), positions within
** bound(levels). */
static void same_as_reference(const char *what, const double *p, uint32_t nv, const uint32_t *f, uint32_t nf,
                              int levels)
{
    ex_loop_mesh m;
    ref_mesh r;
    uint32_t i, bad = 0, first_bad = 0;
    double worst = 0;
    int k;
    if (!module(p, nv, f, nf, levels, &m)) return;
    ref_subdivide(p, nv, f, nf, levels, &r);
    EXPECT(m.triangle_count == r.nf && m.triangle_count == (uint32_t)ex_loop_triangle_count(nf, levels),
           "%s, levels %d: %u triangles, the reference %u (4^levels faces: %u)", what, levels,
           (unsigned)m.triangle_count, (unsigned)r.nf, (unsigned)ex_loop_triangle_count(nf, levels));
    EXPECT(m.vertex_count == r.nv, "%s, levels %d: %u vertices, the reference %u", what, levels,
           (unsigned)m.vertex_count, (unsigned)r.nv);
    for (i = 0; m.triangle_count == r.nf && i < 3 * r.nf; i++) {
        const float *a = m.p + 3 * (size_t)m.indices[i];
        const double *b = r.p + 3 * (size_t)r.f[i];
        double d = 0;
        for (k = 0; k < 3; k++) d = fmax(d, fabs(a[k] - b[k]));
        if (d > bound(levels) && bad++ == 0) first_bad = i;
        worst = fmax(worst, d);
    }
    EXPECT(bad == 0, "%s, levels %d: %u triangle corners differ from the reference's (first: triangle %u corner %u, "
           "off by %g, bound %g)", what, levels, (unsigned)bad, (unsigned)(first_bad / 3), (unsigned)(first_bad % 3),
           worst, bound(levels));
    ex_loop_free(&m);
    ref_free(&r);
}

/* ---- tests ------------------------------------------------------------------ */

/* Levels 0 refines nothing and still pushes to the limit: an octahedron's
** vertices (valence 4: beta 3/32, gamma 1/8) go to half their distance,
** exactly; a centred tetrahedron's (valence 3: beta 3/16, gamma 1/5) to a
** fifth; one triangle's (boundary) to 3/5 p + 1/5 of the other two. */
static void test_levels_zero(void)
{
    ex_loop_mesh m;
    uint32_t i;
    int k, exact = 1, near = 1;
    if (module(octa_p, 6, octa_f, 8, 0, &m)) {
        EXPECT(m.triangle_count == 8 && m.vertex_count == 6 && memcmp(m.indices, octa_f, sizeof octa_f) == 0,
               "octahedron at levels 0: %u triangles, %u vertices, not the control faces", (unsigned)m.triangle_count,
               (unsigned)m.vertex_count);
        for (i = 0; i < 18; i++) exact &= m.p[i] == (float)(octa_p[i] / 2);
        EXPECT(exact, "octahedron at levels 0: vertices not exactly at half their distance (the limit, gamma 1/8)");
        ex_loop_free(&m);
    }
    if (module(tetra_p, 4, tetra_f, 4, 0, &m)) {
        for (i = 0; i < 12; i++) near &= fabs(m.p[i] - tetra_p[i] / 5) <= 4 * FLT_EPSILON;
        EXPECT(near, "tetrahedron at levels 0: vertices not at a fifth of their distance (gamma 1/5)");
        ex_loop_free(&m);
    }
    near = 1;
    if (module(one_p, 3, one_f, 1, 0, &m)) {
        for (i = 0; i < 3; i++)
            for (k = 0; k < 3; k++)
                near &= fabs(m.p[3 * i + k] - (0.6 * one_p[3 * i + k] + 0.2 * (one_p[3 * ((i + 1) % 3) + k]
                                                                        + one_p[3 * ((i + 2) % 3) + k]))) <= 4 * FLT_EPSILON;
        EXPECT(near, "one triangle at levels 0: vertices not at 3/5 p + 1/5 of the others (the boundary limit)");
        ex_loop_free(&m);
    }
}

/* Closed meshes: the tetrahedron (valence 3, beta 3/16) and the
** octahedron (valence 4; new vertices regular, valence 6) at levels 1 to
** 3 against the reference. */
static void test_closed_meshes(void)
{
    int l;
    for (l = 1; l <= 3; l++) {
        same_as_reference("tetrahedron", tetra_p, 4, tetra_f, 4, l);
        same_as_reference("octahedron", octa_p, 6, octa_f, 8, l);
    }
}

/* Properties without the reference, on the octahedron: its mirror
** symmetries survive (every vertex's mirror image is a vertex), and the
** limit points of level L are where level L + 1 puts the same vertices
** (vertex i of level L is vertex i of level L + 1). */
static void test_closed_properties(void)
{
    ex_loop_mesh a, b;
    uint32_t i, j, unmatched = 0, moved = 0;
    int k;
    if (!module(octa_p, 6, octa_f, 8, 2, &a)) return;
    if (!module(octa_p, 6, octa_f, 8, 3, &b)) { ex_loop_free(&a); return; }
    for (i = 0; i < a.vertex_count; i++) {
        const float *p = a.p + 3 * (size_t)i;
        for (k = 0; k < 3; k++) {
            for (j = 0; j < a.vertex_count; j++) {
                const float *q = a.p + 3 * (size_t)j;
                if (fabs(q[k] + p[k]) <= 1e-6 && fabs(q[(k + 1) % 3] - p[(k + 1) % 3]) <= 1e-6
                    && fabs(q[(k + 2) % 3] - p[(k + 2) % 3]) <= 1e-6) break;
            }
            unmatched += j == a.vertex_count;
        }
        for (k = 0; k < 3; k++) moved += fabs(b.p[3 * (size_t)i + k] - p[k]) > bound(3);
    }
    EXPECT(unmatched == 0, "octahedron at levels 2: %u vertices have no mirror image (symmetry lost)", (unsigned)unmatched);
    EXPECT(moved == 0, "octahedron: %u coordinates of level 2's limit points move at level 3 (not on the limit surface)",
           (unsigned)moved);
    ex_loop_free(&a);
    ex_loop_free(&b);
}

/* Open meshes: every vertex of one triangle is on the boundary; a square
** of two triangles has one interior edge.  Flat meshes stay exactly
** flat (each coordinate z is a sum of zeros). */
static void test_open_meshes(void)
{
    ex_loop_mesh m;
    uint32_t i;
    int l, flat = 1;
    for (l = 0; l <= 3; l++) {
        same_as_reference("one triangle", one_p, 3, one_f, 1, l);
        same_as_reference("square", square_p, 4, square_f, 2, l);
    }
    if (module(square_p, 4, square_f, 2, 2, &m)) {
        for (i = 0; i < m.vertex_count; i++) flat &= m.p[3 * (size_t)i + 2] == 0;
        EXPECT(flat, "square at levels 2: a vertex left the plane z = 0");
        ex_loop_free(&m);
    }
}

/* The refusals (see examples/lib/loopsubdiv.h), through the module and
** through the reader, at the Shape's file:line. */
static void refused(const char *what, const char *indices, uint32_t nv, const char *want)
{
    char text[1024], path[512], line[64];
    uint32_t idx[32], nf = 0, v;
    const char *c = indices;
    int used;
    brt_error err;
    ex_pbrt *scene = NULL;
    brt_result r;
    while (sscanf(c, "%u%n", &v, &used) == 1) { idx[nf++] = v; c += used; }
    r = ex_loop_check(idx, nf / 3, nv, &err);
    EXPECT(r == BRT_EPARSE && strstr(err.message, want), "%s: ex_loop_check gave %s (\"%s\"), expected \"%s\"", what,
           brt_result_string(r), r == BRT_OK ? "" : err.message, want);
    snprintf(text, sizeof text, "WorldBegin\n\nShape \"loopsubdiv\" \"integer levels\" 1\n  \"point3 P\" [");
    for (v = 0; v < nv; v++)
        snprintf(text + strlen(text), sizeof text - strlen(text), " %u %u %u", v % 3, v / 3, v % 2);
    snprintf(text + strlen(text), sizeof text - strlen(text), " ] \"integer indices\" [ %s ]\n", indices);
    snprintf(path, sizeof path, "%s", tu_scratch("refused.pbrt"));
    CHECK(tu_spill(path, text, strlen(text)), "cannot write %s", path);
    r = ex_pbrt_open(path, &scene, &err);
    snprintf(line, sizeof line, "refused.pbrt:3: Shape \"loopsubdiv\": ");
    EXPECT(r == BRT_EPARSE && strstr(err.message, line) && strstr(err.message, want) && !strchr(err.message, '\n'),
           "%s: the reader gave %s (\"%s\"), expected \"%s...%s\"", what, brt_result_string(r),
           r == BRT_OK ? "opened" : err.message, line, want);
    ex_pbrt_close(scene);
}

/* ex_pbrt_open refuses text with a message containing want. */
static void opened_badly(const char *what, const char *text, const char *want)
{
    char path[512];
    ex_pbrt *scene = NULL;
    brt_error err;
    brt_result r;
    snprintf(path, sizeof path, "%s", tu_scratch("bad.pbrt"));
    CHECK(tu_spill(path, text, strlen(text)), "cannot write %s", path);
    r = ex_pbrt_open(path, &scene, &err);
    EXPECT(r == BRT_EPARSE && strstr(err.message, want), "%s: the reader gave %s (\"%s\"), expected \"%s\"", what,
           brt_result_string(r), r == BRT_OK ? "opened" : err.message, want);
    ex_pbrt_close(scene);
}

static void test_non_manifold(void)
{
    /* three triangles on edge 0-1 (pbrt-v4 pairs the first two only) */
    refused("three faces on an edge", "0 1 2  1 0 3  0 1 4", 5, "edge 0-1 is in 3 faces");
    /* two faces running 0 -> 1 the same way (pbrt-v4's walk may not end) */
    refused("inconsistent orientation", "0 1 2  0 1 3", 4, "run edge 0-1 the same way");
    /* vertex 4 in no face (pbrt-v4 follows a null face) */
    refused("an unused vertex", "0 1 2  2 1 3", 5, "vertex 4 is in no face");
    /* two fans touching at vertex 0 (pbrt-v4 would weigh one) */
    refused("a bowtie", "0 1 2  0 3 4", 5, "vertex 0: its faces form more than one fan");
    refused("a repeated corner", "0 1 1", 2, "face 0 repeats a vertex");
    /* pbrt-v4 stops on a loopsubdiv without indices, even for 3 points */
    opened_badly("no indices", "WorldBegin\nShape \"loopsubdiv\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n",
                 "bad.pbrt:2: Shape \"loopsubdiv\" without \"integer indices\"");
    opened_badly("levels not an integer", "Shape \"loopsubdiv\" \"integer levels\" 1.5\n",
                 "bad.pbrt:1: \"levels\": expected an integer");
}

/* EX_LOOP_MAX_TRIANGLES (2^20) at the limit and past it: one face at
** levels 10 makes exactly 2^20 triangles and opens; two faces at levels
** 10, and one at 11, are refused at the Shape's line before any
** refinement (a file of a few bytes must not ask for gigabytes). */
static void test_refinement_limit(void)
{
    static const char *const shape = "Shape \"loopsubdiv\" \"point3 P\" [0 0 0 1 0 0 0 1 0";
    char text[512];
    ex_pbrt *scene = NULL;
    brt_error err;
    brt_result r;
    ex_loop_free(NULL);         /* as free(NULL): nothing (loopsubdiv.h) */
    EXPECT(ex_loop_triangle_count(1, 10) == EX_LOOP_MAX_TRIANGLES && EX_LOOP_MAX_TRIANGLES == 1u << 20,
           "one face at levels 10 makes %llu triangles, the limit is %u",
           (unsigned long long)ex_loop_triangle_count(1, 10), (unsigned)EX_LOOP_MAX_TRIANGLES);
    snprintf(text, sizeof text, "WorldBegin\n%s] \"integer indices\" [0 1 2] \"integer levels\" 10\n", shape);
    CHECK(tu_spill(tu_scratch("limit.pbrt"), text, strlen(text)), "cannot write limit.pbrt");
    r = ex_pbrt_open(tu_scratch("limit.pbrt"), &scene, &err);
    EXPECT(r == BRT_OK, "one face at levels 10 (2^20 triangles) refused: %s", r == BRT_OK ? "" : err.message);
    ex_pbrt_close(scene);
    snprintf(text, sizeof text, "WorldBegin\n%s 1 1 0] \"integer indices\" [0 1 2 2 1 3] \"integer levels\" 10\n", shape);
    opened_badly("two faces at levels 10", text, "bad.pbrt:2: Shape \"loopsubdiv\": 2 faces at levels 10 make more than 1048576 triangles");
    snprintf(text, sizeof text, "WorldBegin\n%s] \"integer indices\" [0 1 2] \"integer levels\" 11\n", shape);
    opened_badly("one face at levels 11", text, "bad.pbrt:2: Shape \"loopsubdiv\": 1 faces at levels 11 make more than 1048576 triangles");
}

/* Triangles of pbrt file's world, as streamed. */
typedef struct tris { float *c; uint32_t n; size_t cap; } tris;

static brt_result collect(void *user, const float *corners, uint32_t count, uint32_t first, brt_error *err)
{
    tris *t = user;
    (void)err;
    if (first != t->n) return BRT_EARG;
    if (!(t->c = brt_grow(t->c, &t->cap, 9 * ((size_t)t->n + count), sizeof *t->c))) return BRT_ENOMEM;
    memcpy(t->c + 9 * (size_t)t->n, corners, 9 * (size_t)count * sizeof *corners);
    t->n += count;
    return BRT_OK;
}

static int world_of(const char *name, const char *text, tris *t)
{
    char path[512];
    ex_pbrt *scene;
    brt_scene_source src;
    brt_error err;
    brt_result r;
    memset(t, 0, sizeof *t);
    snprintf(path, sizeof path, "%s", tu_scratch(name));
    if (!tu_spill(path, text, strlen(text))) { test_fail_at(__FILE__, __LINE__, "cannot write %s", path); return 0; }
    if (ex_pbrt_open(path, &scene, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s: %s", name, err.message);
        return 0;
    }
    ex_pbrt_source(scene, &src);
    r = src.world.run ? src.world.run(src.world.user, collect, t, &err) : BRT_EARG;
    ex_pbrt_close(scene);
    if (r != BRT_OK) test_fail_at(__FILE__, __LINE__, "%s: world stream: %s", name, r == BRT_EARG ? "none" : err.message);
    return r == BRT_OK;
}

/* End to end: a pbrt file with a loopsubdiv (an octahedron under a
** Translate and Scale, levels 2 and levels left to the default 3) and
** the reference's refined mesh written as a trianglemesh under the same
** transform: rays from outside at each reference triangle's centroid hit
** that triangle's number in both (its centroid is well inside it: the
** two meshes differ by float rounding only). */
static void test_end_to_end(void)
{
    static const char *const xf = "Translate 1 2 3\nScale 2 2 2\n";
    int levels;
    for (levels = 2; levels <= 3; levels++) {
        size_t cap = 1 << 20, n = 0;
        char *text = malloc(cap);
        tris a, b;
        ref_mesh r;
        uint32_t i, *idx = NULL, wrong = 0, differ = 0;
        brt_bvh *ba = NULL, *bb = NULL;
        int k;
        CHECK(text, "out of memory");
        n += (size_t)snprintf(text + n, cap - n, "WorldBegin\n%sShape \"loopsubdiv\" %s \"point3 P\" [", xf,
                              levels == 2 ? "\"integer levels\" [ 2 ]" : "\"string scheme\" \"loop\"");
        for (i = 0; i < 18; i++) n += (size_t)snprintf(text + n, cap - n, " %g", octa_p[i]);
        n += (size_t)snprintf(text + n, cap - n, " ] \"integer indices\" [");
        for (i = 0; i < 24; i++) n += (size_t)snprintf(text + n, cap - n, " %u", (unsigned)octa_f[i]);
        snprintf(text + n, cap - n, " ]\n");
        if (!world_of("loop.pbrt", text, &a)) { free(text); return; }
        ref_subdivide(octa_p, 6, octa_f, 8, levels, &r);
        n = (size_t)snprintf(text, cap, "WorldBegin\n%sShape \"trianglemesh\" \"point3 P\" [", xf);
        for (i = 0; i < 3 * r.nv; i++) n += (size_t)snprintf(text + n, cap - n, " %.17g", r.p[i]);
        n += (size_t)snprintf(text + n, cap - n, " ] \"integer indices\" [");
        for (i = 0; i < 3 * r.nf; i++) n += (size_t)snprintf(text + n, cap - n, " %u", (unsigned)r.f[i]);
        snprintf(text + n, cap - n, " ]\n");
        n = world_of("reference.pbrt", text, &b);
        free(text);
        if (!n) { free(a.c); ref_free(&r); return; }
        EXPECT(a.n == b.n && a.n == 8u << (2 * levels), "levels %d: loopsubdiv gave %u triangles, the reference %u",
               levels, (unsigned)a.n, (unsigned)b.n);
        idx = malloc(3 * sizeof *idx * (a.n ? a.n : 1));
        for (i = 0; idx && i < 3 * a.n; i++) idx[i] = i;
        if (a.n == b.n && idx && brt_bvh_build(a.c, idx, a.n, NULL, &ba) == BRT_OK
            && brt_bvh_build(b.c, idx, b.n, NULL, &bb) == BRT_OK) {
            for (i = 0; i < b.n; i++) {
                brt_ray ray;
                brt_hit ha, hb;
                for (k = 0; k < 3; k++) {
                    double c = (b.c[9 * i + k] + b.c[9 * i + 3 + k] + b.c[9 * i + 6 + k]) / 3;
                    double centre = k == 0 ? 1 : k == 1 ? 2 : 3;
                    ray.dir[k] = (float)(centre - c);
                    ray.org[k] = (float)(c - 4 * ray.dir[k]);   /* outside: the surface is convex */
                }
                ray.tnear = 0;
                ray.tfar = INFINITY;
                brt_hit_clear(&ha);
                brt_hit_clear(&hb);
                brt_bvh_intersect(ba, &ray, &ha);
                brt_bvh_intersect(bb, &ray, &hb);
                wrong += hb.prim != i;
                differ += ha.prim != hb.prim || fabs(ha.t - hb.t) > 1e-5;
            }
            EXPECT(wrong == 0, "levels %d: %u rays at reference triangles' centroids hit another", levels, (unsigned)wrong);
            EXPECT(differ == 0, "levels %d: %u of %u rays hit another loopsubdiv triangle than the reference's",
                   levels, (unsigned)differ, (unsigned)b.n);
        } else EXPECT(0, "could not build the BVHs");
        brt_bvh_free(ba);
        brt_bvh_free(bb);
        free(idx);
        free(a.c);
        free(b.c);
        ref_free(&r);
    }
}

void suite_loopsubdiv(void)
{
    test_run("loopsubdiv: levels 0 is the control mesh pushed to the limit (closed forms)", test_levels_zero);
    test_run("loopsubdiv: closed meshes == the reference (tetrahedron, octahedron, levels 1-3)", test_closed_meshes);
    test_run("loopsubdiv: symmetry kept, limit points stay at the next level", test_closed_properties);
    test_run("loopsubdiv: open meshes' boundary rules == the reference; flat stays flat", test_open_meshes);
    test_run("loopsubdiv: non-manifold input refused at file:line", test_non_manifold);
    test_run("loopsubdiv: 2^20 triangles after refining opens, more refused", test_refinement_limit);
    test_run("loopsubdiv: a pbrt loopsubdiv hits as the reference's trianglemesh", test_end_to_end);
}
