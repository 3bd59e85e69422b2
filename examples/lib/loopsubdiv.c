/*
** examples/lib/loopsubdiv.c -- Loop subdivision as pbrt-v4 refines a Shape
** "loopsubdiv" (the manual is examples/lib/loopsubdiv.h).  It follows
** pbrt-v4's src/pbrt/util/loopsubdiv.cpp step by step, with its names:
** SDVertex and SDFace become sd_vertex and sd_face, pointers become
** indices, and a face's children are implicit (face i of one level has
** children 4i .. 4i+3 in the next, vertex i's child is vertex i), which
** is the order in which pbrt-v4 allocates and lists them.
**
**   1. the control mesh: faces, neighbours across edges, each vertex's
**      start face, boundary and regular flags (and the checks);
**   2. one level of refinement: even vertices, odd (edge) vertices, the
**      new faces' neighbours and corners;
**   3. the push to the limit surface and the output mesh.
*/
#include "loopsubdiv.h"

#include <stdlib.h>
#include <string.h>

#define NONE 0xFFFFFFFFu            /* no face (pbrt's nullptr) */
#define NEXT(i) (((i) + 1) % 3)
#define PREV(i) (((i) + 2) % 3)

/* A vertex of one level: pbrt's SDVertex (its child is the vertex of the
** same number in the next level). */
typedef struct sd_vertex {
    float p[3];
    uint32_t start;                 /* startFace: one face holding it */
    unsigned char boundary, regular;
} sd_vertex;

/* A triangle of one level: pbrt's SDFace.  f[i] is the neighbour across
** the edge v[i] -> v[NEXT(i)], NONE on a boundary. */
typedef struct sd_face {
    uint32_t v[3], f[3];
} sd_face;

typedef struct sd_mesh {
    sd_vertex *v;
    sd_face *f;
    uint32_t nv, nf;
} sd_mesh;

/* A one-ring, as vertex numbers; grown as valences need. */
typedef struct ring {
    uint32_t *v;
    size_t cap;
} ring;

static void mesh_free(sd_mesh *m)
{
    free(m->v);
    free(m->f);
    memset(m, 0, sizeof *m);
}

static brt_result mesh_alloc(sd_mesh *m, uint64_t nv, uint64_t nf, brt_error *err)
{
    memset(m, 0, sizeof *m);
    if (nv > EX_LOOP_MAX_TRIANGLES || nf > EX_LOOP_MAX_TRIANGLES)
        return brt_fail(err, BRT_EPARSE, "the refined mesh would have more than %lu vertices or triangles",
                        (unsigned long)EX_LOOP_MAX_TRIANGLES);
    m->v = malloc((nv ? nv : 1) * sizeof *m->v);
    m->f = malloc((nf ? nf : 1) * sizeof *m->f);
    if (!m->v || !m->f) {
        mesh_free(m);
        return brt_fail(err, BRT_ENOMEM, "out of memory refining a loopsubdiv mesh (%llu triangles)",
                        (unsigned long long)nf);
    }
    m->nv = (uint32_t)nv;
    m->nf = (uint32_t)nf;
    return BRT_OK;
}

/* ---- walking around a vertex (SDFace's methods) --------------------- */

/* Which corner of face f vertex v is (the checks make it one of the three). */
static int vnum(const sd_mesh *m, uint32_t f, uint32_t v)
{
    const sd_face *face = &m->f[f];
    return face->v[0] == v ? 0 : face->v[1] == v ? 1 : 2;
}

static uint32_t next_face(const sd_mesh *m, uint32_t f, uint32_t v) { return m->f[f].f[vnum(m, f, v)]; }
static uint32_t prev_face(const sd_mesh *m, uint32_t f, uint32_t v) { return m->f[f].f[PREV(vnum(m, f, v))]; }
static uint32_t next_vert(const sd_mesh *m, uint32_t f, uint32_t v) { return m->f[f].v[NEXT(vnum(m, f, v))]; }
static uint32_t prev_vert(const sd_mesh *m, uint32_t f, uint32_t v) { return m->f[f].v[PREV(vnum(m, f, v))]; }

/* SDVertex::valence: the faces around an interior vertex; around a
** boundary vertex, its faces + 1, which is its number of neighbours. */
static uint32_t valence(const sd_mesh *m, uint32_t v)
{
    uint32_t start = m->v[v].start, f = start, n = 1;
    if (!m->v[v].boundary) {
        while ((f = next_face(m, f, v)) != start) n++;
        return n;
    }
    while ((f = next_face(m, f, v)) != NONE) n++;
    f = start;
    while ((f = prev_face(m, f, v)) != NONE) n++;
    return n + 1;
}

/* SDVertex::oneRing: the neighbours in pbrt's order.  Interior: from the
** start face around through next faces.  Boundary: from the last face
** of the next-face direction, its next vertex, then back through every
** face's previous vertex: ring[0] and ring[n-1] are the two neighbours
** along the boundary.  Returns the valence, 0 when out of memory. */
static uint32_t one_ring(const sd_mesh *m, uint32_t v, ring *r)
{
    uint32_t n = valence(m, v), k = 0, f = m->v[v].start, f2;
    if (n > r->cap) {
        uint32_t *bigger = realloc(r->v, n * sizeof *bigger);
        if (!bigger) return 0;
        r->v = bigger;
        r->cap = n;
    }
    if (!m->v[v].boundary) {
        do {
            r->v[k++] = next_vert(m, f, v);
            f = next_face(m, f, v);
        } while (f != m->v[v].start);
        return n;
    }
    while ((f2 = next_face(m, f, v)) != NONE) f = f2;
    r->v[k++] = next_vert(m, f, v);
    do {
        r->v[k++] = prev_vert(m, f, v);
        f = prev_face(m, f, v);
    } while (f != NONE);
    return n;
}

/* ---- the weights (pbrt's beta, loopGamma, weightOneRing, weightBoundary) */

/* Loop's beta for valence n, as pbrt-v4 takes it: 3/16 for n = 3, else
** Warren's 3 / (8 n), which is 1/16 for the regular n = 6. */
static float beta(uint32_t n)
{
    float eight_n;
    if (n == 3) return 3.0f / 16.0f;
    eight_n = 8.0f * (float)n;
    return 3.0f / eight_n;
}

/* The limit-surface weight of the one-ring: 1 / (n + 3 / (8 beta)).
** Each step is stored in a float, as pbrt's Float expression rounds it. */
static float loop_gamma(uint32_t n)
{
    float b = beta(n), q = 8.0f * b;
    q = 3.0f / q;
    q = (float)n + q;
    return 1.0f / q;
}

/* out += w * q, component by component (pbrt's p += w * q). */
static void add_scaled(float out[3], float w, const float q[3])
{
    int k;
    for (k = 0; k < 3; k++) {
        float t = w * q[k];
        out[k] = out[k] + t;
    }
}

/* weightOneRing: (1 - n b) p + b * (each neighbour, in ring order). */
static int weight_one_ring(const sd_mesh *m, uint32_t v, float b, ring *r, float out[3])
{
    uint32_t n = one_ring(m, v, r), i;
    float self;
    int k;
    if (n == 0) return 0;
    self = (float)n * b;
    self = 1.0f - self;
    for (k = 0; k < 3; k++) out[k] = self * m->v[v].p[k];
    for (i = 0; i < n; i++) add_scaled(out, b, m->v[r->v[i]].p);
    return 1;
}

/* weightBoundary: (1 - 2 b) p + b * (the two boundary neighbours). */
static int weight_boundary(const sd_mesh *m, uint32_t v, float b, ring *r, float out[3])
{
    uint32_t n = one_ring(m, v, r);
    float self = 1.0f - 2.0f * b;
    int k;
    if (n == 0) return 0;
    for (k = 0; k < 3; k++) out[k] = self * m->v[v].p[k];
    add_scaled(out, b, m->v[r->v[0]].p);
    add_scaled(out, b, m->v[r->v[n - 1]].p);
    return 1;
}

/* ---- 1. the control mesh ------------------------------------------------ */

/* A face's edge, for pairing faces: its ends sorted, and which face and
** edge it is (3 f + k). */
typedef struct half_edge { uint32_t lo, hi, fk; } half_edge;

static int half_edge_order(const void *a, const void *b)
{
    const half_edge *x = a, *y = b;
    if (x->lo != y->lo) return x->lo < y->lo ? -1 : 1;
    if (x->hi != y->hi) return x->hi < y->hi ? -1 : 1;
    return x->fk < y->fk ? -1 : x->fk > y->fk;
}

/* LoopSubdivide's first steps: faces' corners, each vertex's start face
** (the last face holding it, as pbrt's loop leaves it), the neighbour
** pointers (pbrt pairs the faces of an edge through a std::set; sorting
** the edges pairs the same faces), then boundary and regular flags.
** Positions may be NULL (ex_loop_check).  The checks come where pbrt's
** walks would first go wrong (see the header). */
static brt_result build_control(const float *p, uint32_t nv, const uint32_t *idx, uint32_t nf, sd_mesh *m,
                                brt_error *err)
{
    half_edge *e = NULL;
    uint32_t *faces_at = NULL;      /* faces holding each vertex, for the fan check */
    uint64_t i, j;
    brt_result r = mesh_alloc(m, nv, nf, err);
    if (r != BRT_OK) return r;
    e = malloc(3 * (size_t)(nf ? nf : 1) * sizeof *e);
    faces_at = calloc(nv ? nv : 1, sizeof *faces_at);
    if (!e || !faces_at) { r = brt_fail(err, BRT_ENOMEM, "out of memory for a loopsubdiv mesh"); goto done; }
    for (i = 0; i < nv; i++) {
        if (p) memcpy(m->v[i].p, p + 3 * i, sizeof m->v[i].p);
        m->v[i].start = NONE;
    }
    for (i = 0; i < nf; i++) {
        sd_face *f = &m->f[i];
        for (j = 0; j < 3; j++) {
            uint32_t v = idx[3 * i + j];
            if (v >= nv) { r = brt_fail(err, BRT_EPARSE, "index %lu out of range (%lu vertices)", (unsigned long)v,
                                        (unsigned long)nv); goto done; }
            f->v[j] = v;
            f->f[j] = NONE;
            m->v[v].start = (uint32_t)i;
            faces_at[v]++;
        }
        if (f->v[0] == f->v[1] || f->v[1] == f->v[2] || f->v[2] == f->v[0]) {
            r = brt_fail(err, BRT_EPARSE, "face %lu repeats a vertex (%lu %lu %lu)", (unsigned long)i,
                         (unsigned long)f->v[0], (unsigned long)f->v[1], (unsigned long)f->v[2]);
            goto done;
        }
        for (j = 0; j < 3; j++) {
            uint32_t a = f->v[j], b = f->v[NEXT(j)];
            half_edge *h = &e[3 * i + j];
            h->lo = a < b ? a : b;
            h->hi = a < b ? b : a;
            h->fk = (uint32_t)(3 * i + j);
        }
    }
    for (i = 0; i < nv; i++)
        if (m->v[i].start == NONE) {   /* pbrt would follow a null start face */
            r = brt_fail(err, BRT_EPARSE, "vertex %lu is in no face", (unsigned long)i);
            goto done;
        }
    qsort(e, 3 * (size_t)nf, sizeof *e, half_edge_order);
    for (i = 0; i < 3 * (uint64_t)nf; i = j) {
        uint32_t f0, k0, f1, k1;
        for (j = i + 1; j < 3 * (uint64_t)nf && e[j].lo == e[i].lo && e[j].hi == e[i].hi; j++) {}
        if (j - i == 1) continue;   /* a boundary edge */
        if (j - i > 2) {
            r = brt_fail(err, BRT_EPARSE, "edge %lu-%lu is in %lu faces (non-manifold; at most 2)",
                         (unsigned long)e[i].lo, (unsigned long)e[i].hi, (unsigned long)(j - i));
            goto done;
        }
        f0 = e[i].fk / 3; k0 = e[i].fk % 3;
        f1 = e[i + 1].fk / 3; k1 = e[i + 1].fk % 3;
        /* Neighbours must run the edge opposite ways: walking next faces
        ** around a vertex then visits each face once (pbrt relies on it). */
        if (m->f[f0].v[k0] == m->f[f1].v[k1]) {
            r = brt_fail(err, BRT_EPARSE, "faces %lu and %lu run edge %lu-%lu the same way (inconsistent orientation)",
                         (unsigned long)f0, (unsigned long)f1, (unsigned long)m->f[f0].v[k0],
                         (unsigned long)m->f[f0].v[NEXT(k0)]);
            goto done;
        }
        m->f[f0].f[k0] = f1;
        m->f[f1].f[k1] = f0;
    }
    /* "Finish vertex initialization": a walk through next faces from the
    ** start face that ends on no face means a boundary vertex. */
    for (i = 0; i < nv; i++) {
        sd_vertex *v = &m->v[i];
        uint32_t f = v->start, n, fan;
        do f = next_face(m, f, (uint32_t)i); while (f != NONE && f != v->start);
        v->boundary = f == NONE;
        n = valence(m, (uint32_t)i);
        v->regular = v->boundary ? n == 4 : n == 6;
        fan = v->boundary ? n - 1 : n;
        if (fan != faces_at[i]) {   /* pbrt's walk would see only one fan */
            r = brt_fail(err, BRT_EPARSE, "vertex %lu: its faces form more than one fan (non-manifold)",
                         (unsigned long)i);
            goto done;
        }
    }
done:
    free(e);
    free(faces_at);
    if (r != BRT_OK) mesh_free(m);
    return r;
}

/* ---- 2. one level of refinement ------------------------------------------- */

/* The edge of face g that runs v0 -> v1 backwards (from v1 to v0). */
static int edge_back(const sd_mesh *m, uint32_t g, uint32_t v0, uint32_t v1)
{
    int j;
    for (j = 0; j < 2; j++)
        if (m->f[g].v[j] == v1 && m->f[g].v[NEXT(j)] == v0) return j;
    return 2;
}

/* The corner of face f that is neither a nor b (SDFace::otherVert). */
static uint32_t other_vert(const sd_mesh *m, uint32_t f, uint32_t a, uint32_t b)
{
    const uint32_t *v = m->f[f].v;
    return v[0] != a && v[0] != b ? v[0] : v[1] != a && v[1] != b ? v[1] : v[2];
}

/* One pass of LoopSubdivide's level loop: cur -> nxt. */
static brt_result refine(const sd_mesh *cur, sd_mesh *nxt, ring *rg, brt_error *err)
{
    uint32_t *odd = NULL;           /* odd vertex of each face's edge k: 3 f + k */
    uint64_t edges = 0;
    uint32_t f, k, i, made;
    brt_result r;
    /* An interior edge is made by the first of its faces, a boundary edge
    ** by its one face: count them first to size the next level. */
    for (f = 0; f < cur->nf; f++)
        for (k = 0; k < 3; k++) edges += cur->f[f].f[k] == NONE || cur->f[f].f[k] > f;
    if ((r = mesh_alloc(nxt, (uint64_t)cur->nv + edges, 4 * (uint64_t)cur->nf, err)) != BRT_OK) return r;
    if (!(odd = malloc(3 * (size_t)cur->nf * sizeof *odd))) goto no_memory;

    /* Even vertices: "Update vertex positions for even vertices".  The
    ** regular flag, not the valence, picks 1/16 (it is valence 6). */
    for (i = 0; i < cur->nv; i++) {
        const sd_vertex *v = &cur->v[i];
        sd_vertex *c = &nxt->v[i];
        int ok;
        c->boundary = v->boundary;
        c->regular = v->regular;
        if (!v->boundary) ok = weight_one_ring(cur, i, v->regular ? 1.0f / 16.0f : beta(valence(cur, i)), rg, c->p);
        else ok = weight_boundary(cur, i, 1.0f / 8.0f, rg, c->p);
        if (!ok) goto no_memory;
        /* "Update even vertex face pointers": the child of the start face
        ** at this vertex's corner. */
        c->start = 4 * v->start + (uint32_t)vnum(cur, v->start, i);
    }

    /* Odd vertices: "Compute new odd edge vertices", made in face order,
    ** edges v0v1, v1v2, v2v0, when an edge is first met. */
    made = cur->nv;
    for (f = 0; f < cur->nf; f++)
        for (k = 0; k < 3; k++) {
            const sd_face *face = &cur->f[f];
            uint32_t g = face->f[k], a = face->v[k], b = face->v[NEXT(k)];
            sd_vertex *c;
            int j;
            if (g != NONE && g < f) continue;   /* made with face g */
            c = &nxt->v[made];
            odd[3 * f + k] = made;
            if (g != NONE) odd[3 * g + (uint32_t)edge_back(cur, g, a, b)] = made;
            made++;
            c->regular = 1;
            c->boundary = g == NONE;
            c->start = 4 * f + 3;   /* the middle child */
            if (c->boundary) {      /* the midpoint */
                for (j = 0; j < 3; j++) c->p[j] = 0.5f * cur->v[a].p[j];
                add_scaled(c->p, 0.5f, cur->v[b].p);
            } else {                /* 3/8 each end, 1/8 each opposite corner */
                for (j = 0; j < 3; j++) c->p[j] = 3.0f / 8.0f * cur->v[a].p[j];
                add_scaled(c->p, 3.0f / 8.0f, cur->v[b].p);
                add_scaled(c->p, 1.0f / 8.0f, cur->v[other_vert(cur, f, a, b)].p);
                add_scaled(c->p, 1.0f / 8.0f, cur->v[other_vert(cur, g, a, b)].p);
            }
        }

    /* The new faces: "Update face neighbor pointers" and "Update face
    ** vertex pointers".  Children 0..2 sit at corners 0..2, child 3 in
    ** the middle; child j's neighbours across the parent's edges are the
    ** children of the parent's neighbours at the same corner. */
    for (f = 0; f < cur->nf; f++) {
        const sd_face *face = &cur->f[f];
        sd_face *ch = &nxt->f[4 * (size_t)f];
        uint32_t j;
        for (j = 0; j < 3; j++) {
            uint32_t g = face->f[j], h = face->f[PREV(j)], m = odd[3 * f + j];
            ch[3].f[j] = 4 * f + NEXT(j);
            ch[j].f[NEXT(j)] = 4 * f + 3;
            ch[j].f[j] = g != NONE ? 4 * g + (uint32_t)vnum(cur, g, face->v[j]) : NONE;
            ch[j].f[PREV(j)] = h != NONE ? 4 * h + (uint32_t)vnum(cur, h, face->v[j]) : NONE;
            ch[j].v[j] = face->v[j];    /* the even vertex keeps its number */
            ch[j].v[NEXT(j)] = m;
            ch[NEXT(j)].v[j] = m;
            ch[3].v[j] = m;
        }
    }
    free(odd);
    return BRT_OK;
no_memory:
    free(odd);
    mesh_free(nxt);
    return brt_fail(err, BRT_ENOMEM, "out of memory refining a loopsubdiv mesh");
}

/* ---- 3. the limit surface and the output ---------------------------------- */

uint64_t ex_loop_triangle_count(uint64_t faces, int levels)
{
    int i;
    for (i = 0; i < levels; i++) {
        if (faces > UINT64_MAX / 4) return UINT64_MAX;
        faces *= 4;
    }
    return faces;
}

brt_result ex_loop_check(const uint32_t *indices, uint32_t face_count, uint32_t vertex_count, brt_error *err)
{
    sd_mesh m;
    brt_result r = build_control(NULL, vertex_count, indices, face_count, &m, err);
    mesh_free(&m);
    return r;
}

void ex_loop_free(ex_loop_mesh *mesh)
{
    if (!mesh) return;
    free(mesh->p);
    free(mesh->indices);
    memset(mesh, 0, sizeof *mesh);
}

brt_result ex_loop_subdivide(const float *p, uint32_t vertex_count, const uint32_t *indices,
                             uint32_t face_count, int levels, ex_loop_mesh *out, brt_error *err)
{
    sd_mesh cur, nxt;
    ring rg = {NULL, 0};
    uint32_t i;
    int level;
    brt_result r;
    memset(out, 0, sizeof *out);
    if (ex_loop_triangle_count(face_count, levels) > EX_LOOP_MAX_TRIANGLES)
        return brt_fail(err, BRT_EPARSE, "%lu faces at levels %d make more than %lu triangles",
                        (unsigned long)face_count, levels, (unsigned long)EX_LOOP_MAX_TRIANGLES);
    if ((r = build_control(p, vertex_count, indices, face_count, &cur, err)) != BRT_OK) return r;
    for (level = 0; level < levels; level++) {
        r = refine(&cur, &nxt, &rg, err);
        mesh_free(&cur);
        if (r != BRT_OK) { free(rg.v); return r; }
        cur = nxt;
    }
    /* "Push vertices to limit surface": every limit point from the last
    ** level's positions, so they are computed before any is replaced. */
    out->p = malloc(3 * (size_t)(cur.nv ? cur.nv : 1) * sizeof *out->p);
    out->indices = malloc(3 * (size_t)(cur.nf ? cur.nf : 1) * sizeof *out->indices);
    if (!out->p || !out->indices) goto no_memory;
    for (i = 0; i < cur.nv; i++) {
        int ok = cur.v[i].boundary ? weight_boundary(&cur, i, 1.0f / 5.0f, &rg, out->p + 3 * (size_t)i)
                                   : weight_one_ring(&cur, i, loop_gamma(valence(&cur, i)), &rg, out->p + 3 * (size_t)i);
        if (!ok) goto no_memory;
    }
    for (i = 0; i < cur.nf; i++) memcpy(out->indices + 3 * (size_t)i, cur.f[i].v, 3 * sizeof *out->indices);
    out->vertex_count = cur.nv;
    out->triangle_count = cur.nf;
    mesh_free(&cur);
    free(rg.v);
    return BRT_OK;
no_memory:
    mesh_free(&cur);
    free(rg.v);
    ex_loop_free(out);
    return brt_fail(err, BRT_ENOMEM, "out of memory refining a loopsubdiv mesh");
}
