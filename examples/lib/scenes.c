/*
** examples/lib/scenes.c -- the built-in procedural scenes: stand-ins for the
** crown, landscape and island scenes of Molenaar and Eisemann (2020),
** "Conservative Ray Batching using Geometry Proxies".
**
** HOW A SCENE IS MADE
** Every piece of geometry is one parametric surface sampled on a grid of
** "segments" (u) by "rings" (v), with a topology given by flags: u and v
** may wrap around (a tube, a torus), and a single pole vertex may close
** either end of v (a sphere, a cone, an island with its peak).  Grids are
** indexed meshes, so a closed surface is closed by construction, whatever
** its shape: the crown's watertightness does not depend on floating point.
** A surface is placed by an affine transform (rotation, uniform scale,
** translation).
**
** OUTPUTS AND MEMORY
** The builders describe a scene surface by surface; emit_surface makes
** each surface ring by ring and hands vertices and triangles on in batches
** to one of three outputs: counts only (mkscene writes them in its header
** before the first vertex), an indexed mesh (vertices and index triples,
** to ex_mesh_sink: the collector ex_scene_generate and mkscene's writer),
** or a triangle stream (corners, to brt_triangle_fn: the streamed scene
** build).  The builder holds one batch, three rings of the current surface
** and the placement of the current object, so its memory does not grow
** with the scale; only the collector holds the scene.  Each output sees
** the same triangles in the same order, so they agree bit for bit.
**
** SIZE
** The crown gets a triangle budget of 100000 * scale, shared out between
** its parts as finer grids; the landscape and the island: scenes.h.
**
** ONE GENERATION: THE INSTANCED LANDSCAPE AND ISLAND (the last sections)
** The same builders make the instanced landscape and island part by
** part: the world (terrain, or sea and islands) and each prototype are a
** builder run of their own, counted (OUT_COUNT, with mark_material's part
** log for the colours) when the scene is opened and streamed
** (OUT_TRIANGLES) on demand.  Instances are never built as geometry:
** instance i is a transform drawn from (seed, i), standing on the world's
** own triangles (grid_vertex recomputes the very floats emit_surface
** makes, so the base point lies on the plane that is rendered).  As a
** mesh they are baked (bake): the world part, then every instance's
** prototype through the instance's matrix.
*/
#include "scenes.h"
#include "common.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define PI 3.14159265358979323846
#define TRIANGLES_PER_SCALE 100000.0

/* ===================================================================== */
/* Small vector helpers and placements                                   */
/* ===================================================================== */

/* p' = m p + t, with m a rotation times a uniform positive scale (so a
** placement never flips the orientation of triangles). */
typedef struct xform {
    double m[3][3];
    double t[3];
} xform;

/* Local x goes to x_axis, local y to y_axis (orthonormal), local z to their
** cross product; then scale and move to `at`. */
static xform xform_frame(const double x_axis[3], const double y_axis[3],
                         double scale, const double at[3])
{
    xform x;
    double z_axis[3];
    int r;
    ex_cross3(x_axis, y_axis, z_axis);
    for (r = 0; r < 3; r++) {
        x.m[r][0] = scale * x_axis[r];
        x.m[r][1] = scale * y_axis[r];
        x.m[r][2] = scale * z_axis[r];
        x.t[r] = at[r];
    }
    return x;
}

/* Points local y along `axis`, turned by `roll` about it.  With roll 0 and
** a non-vertical axis, local z points as far down as it can: leaves and
** fronds that bend along +z droop. */
static xform xform_along(const double axis[3], double roll, double scale,
                         const double at[3])
{
    double y[3], x[3], side[3], helper[3] = {0, 1, 0};
    int k;
    memcpy(y, axis, sizeof y);
    ex_normalize3(y);
    if (fabs(y[1]) > 0.99) { helper[0] = 1; helper[1] = 0; }
    ex_cross3(helper, y, x);
    ex_normalize3(x);
    ex_cross3(y, x, side);
    for (k = 0; k < 3; k++) x[k] = x[k] * cos(roll) + side[k] * sin(roll);
    return xform_frame(x, y, scale, at);
}

static double clamp(double x, double lo, double hi)
{
    return x < lo ? lo : x > hi ? hi : x;
}

static double rnd(uint64_t *rng, double lo, double hi)
{
    return lo + (hi - lo) * (double)brt_random_float(rng);
}

/* A direction around +y, at most max_tilt radians away from it. */
static void random_up(uint64_t *rng, double max_tilt, double out[3])
{
    double tilt = rnd(rng, 0, max_tilt), azimuth = rnd(rng, 0, 2 * PI);
    out[0] = sin(tilt) * cos(azimuth);
    out[1] = cos(tilt);
    out[2] = sin(tilt) * sin(azimuth);
}

/* ===================================================================== */
/* Gridded surfaces and the builder                                      */
/* ===================================================================== */

enum { WRAP_U = 1, WRAP_V = 2, POLE_START = 4, POLE_END = 8 };
#define SPHERE_LIKE (WRAP_U | POLE_START | POLE_END)

typedef struct grid {
    uint32_t segs;    /* vertices per ring (u) */
    uint32_t rings;   /* rings of vertices (v), poles not counted */
    unsigned flags;
} grid;

/* A surface point for u, v in [0, 1]; the poles are at v = 0 and v = 1. */
typedef void (*surface_fn)(const void *shape, double u, double v, double p[3]);

/* What the builder makes of the surfaces (see OUTPUTS at the top). */
enum output { OUT_COUNT, OUT_INDEXED, OUT_TRIANGLES };

#define BATCH 8192   /* vertices, index triples or corner triples per hand-over */

/* The parts of a mesh by material (instanced scenes' colours): part k
** starts at triangle start[k] and runs to the next part's start. */
#define MAX_PARTS 8
typedef struct part_log {
    uint32_t count;
    uint64_t start[MAX_PARTS];
    unsigned char material[MAX_PARTS];   /* ex_material */
} part_log;

typedef struct builder {
    enum output out;
    ex_mesh_sink sink;             /* OUT_INDEXED */
    brt_triangle_fn emit;          /* OUT_TRIANGLES */
    void *emit_user;
    const char *name;              /* for messages */
    double scale;
    brt_error *err;
    uint64_t vertices, triangles;  /* made so far: the number of the next one */
    float *vertex_batch;           /* BATCH vertices awaiting the sink */
    uint32_t vertex_pending;
    void *triangle_batch;          /* BATCH index triples or corner triples */
    uint32_t triangle_pending;
    float *rings[3];               /* one surface's first ring and two rolling ones */
    uint32_t ring_cap;             /* vertices each ring buffer holds */
    part_log *parts;               /* NULL, or where mark_material records parts */
    brt_result failed;             /* the first failure (err says what) */
} builder;

static void out_of_memory(brt_error *err, const char *name, double scale)
{
    brt_fail(err, BRT_ENOMEM, "%s: out of memory at scale %g", name, scale);
}

static void fail_out_of_memory(builder *b)
{
    out_of_memory(b->err, b->name, b->scale);
    b->failed = BRT_ENOMEM;
}

static uint32_t grid_poles(const grid *g)
{
    return ((g->flags & POLE_START) != 0) + ((g->flags & POLE_END) != 0);
}

static uint64_t grid_vertices(const grid *g)
{
    return (uint64_t)g->segs * g->rings + grid_poles(g);
}

static uint64_t grid_triangles(const grid *g)
{
    uint64_t cols = (g->flags & WRAP_U) ? g->segs : g->segs - 1;
    uint64_t bands = (g->flags & WRAP_V) ? g->rings : g->rings - 1;
    return 2 * cols * bands + (uint64_t)g->segs * grid_poles(g);
}

/* The segments and rings of a sphere-like grid of about `triangles`
** triangles whose segments outnumber its rings `aspect` times (chosen
** per shape so that its triangles come out roughly equilateral). */
static grid grid_for_budget(double triangles, double aspect, unsigned flags)
{
    grid g;
    double rings = sqrt(triangles / (2 * aspect));
    g.rings = rings < 2 ? 2 : (uint32_t)rings;
    g.segs = aspect * rings < 3 ? 3 : (uint32_t)(aspect * rings);
    g.flags = flags;
    return g;
}

static double grid_v(const grid *g, uint32_t ring)
{
    uint32_t start = (g->flags & POLE_START) != 0;
    if (g->flags & WRAP_V) return (double)ring / g->rings;
    return (double)(ring + start) / (double)(g->rings - 1 + grid_poles(g));
}

static void put_vertex(float *out, const xform *x, const double p[3])
{
    int r;
    for (r = 0; r < 3; r++)
        out[r] = (float)(x->m[r][0] * p[0] + x->m[r][1] * p[1] + x->m[r][2] * p[2] + x->t[r]);
}

/* ---- handing vertices and triangles on, a batch at a time ---- */

static void flush_vertices(builder *b)
{
    brt_result r;
    if (b->vertex_pending == 0 || b->failed) return;
    r = b->sink.vertices(b->sink.user, b->vertex_batch, b->vertex_pending, b->err);
    b->vertex_pending = 0;
    if (r != BRT_OK) b->failed = r;
}

static void flush_triangles(builder *b)
{
    brt_result r;
    uint32_t n = b->triangle_pending;
    if (n == 0 || b->failed) return;
    if (b->out == OUT_INDEXED)
        r = b->sink.triangles(b->sink.user, b->triangle_batch, n, b->err);
    else   /* the numbers fit: emit_surface refuses more than 2^32 - 1 */
        r = b->emit(b->emit_user, b->triangle_batch, n, (uint32_t)(b->triangles - n), b->err);
    b->triangle_pending = 0;
    if (r != BRT_OK) b->failed = r;
}

/* Vertices go on only in indexed output: a triangle stream carries
** positions in its corners. */
static void put_vertices(builder *b, const float *xyz, uint32_t count)
{
    while (b->out == OUT_INDEXED && count > 0 && !b->failed) {
        uint32_t n = BATCH - b->vertex_pending;
        if (n > count) n = count;
        memcpy(b->vertex_batch + 3 * (size_t)b->vertex_pending, xyz, 12 * (size_t)n);
        b->vertex_pending += n;
        xyz += 3 * (size_t)n;
        count -= n;
        if (b->vertex_pending == BATCH) flush_vertices(b);
    }
}

/* A vertex of the surface being made: where its position is (in a ring
** buffer) and its number in the mesh. */
typedef struct corner {
    const float *p;
    uint64_t index;
} corner;

/* A ring of vertices: positions and the number of the first. */
typedef struct ring {
    const float *xyz;
    uint64_t first;
} ring;

static corner ring_corner(const ring *r, uint32_t j)
{
    corner c;
    c.p = r->xyz + 3 * (size_t)j;
    c.index = r->first + j;
    return c;
}

static void put_triangle(builder *b, corner a, corner c, corner d)
{
    if (b->out == OUT_INDEXED) {
        uint32_t *t = (uint32_t *)b->triangle_batch + 3 * (size_t)b->triangle_pending;
        t[0] = (uint32_t)a.index;
        t[1] = (uint32_t)c.index;
        t[2] = (uint32_t)d.index;
    } else {
        float *t = (float *)b->triangle_batch + 9 * (size_t)b->triangle_pending;
        memcpy(t, a.p, 12);
        memcpy(t + 3, c.p, 12);
        memcpy(t + 6, d.p, 12);
    }
    b->triangles++;
    if (++b->triangle_pending == BATCH) flush_triangles(b);
}

/* ---- surfaces ---- */

typedef struct surface {
    const grid *g;
    surface_fn fn;
    const void *shape;
    const xform *x;
} surface;

/* The positions of ring i (segs vertices) into out. */
static void surface_ring(const surface *s, uint32_t i, float *out)
{
    uint32_t segs = s->g->segs, j;
    double p[3], v = grid_v(s->g, i), du = 1.0 / ((s->g->flags & WRAP_U) ? segs : segs - 1);
    for (j = 0; j < segs; j++) {
        s->fn(s->shape, j * du, v, p);
        put_vertex(out + 3 * (size_t)j, s->x, p);
    }
}

/* Ring buffers for rings of segs vertices (kept and grown across surfaces). */
static int reserve_rings(builder *b, uint32_t segs)
{
    int k;
    if (segs <= b->ring_cap) return 1;
    for (k = 0; k < 3; k++) {
        float *bigger = realloc(b->rings[k], 12 * (size_t)segs);
        if (!bigger) {
            fail_out_of_memory(b);
            return 0;
        }
        b->rings[k] = bigger;
    }
    b->ring_cap = segs;
    return 1;
}

/* The triangles of the band between rings lo and hi (quads split along
** one diagonal). */
static void put_band(builder *b, const surface *s, const ring *lo, const ring *hi)
{
    uint32_t segs = s->g->segs, j;
    uint32_t cols = (s->g->flags & WRAP_U) ? segs : segs - 1;
    for (j = 0; j < cols; j++) {
        uint32_t j2 = (j + 1) % segs;
        put_triangle(b, ring_corner(lo, j), ring_corner(lo, j2), ring_corner(hi, j2));
        put_triangle(b, ring_corner(lo, j), ring_corner(hi, j2), ring_corner(hi, j));
    }
}

/* The fan between a pole and a ring; towards the start pole it runs
** against the ring's order, towards the end pole with it. */
static void put_fan(builder *b, uint32_t segs, const ring *pole, const ring *r, int start)
{
    uint32_t j;
    for (j = 0; j < segs; j++) {
        corner here = ring_corner(r, j), next = ring_corner(r, (j + 1) % segs);
        if (start) put_triangle(b, ring_corner(pole, 0), next, here);
        else put_triangle(b, ring_corner(pole, 0), here, next);
    }
}

/* Whether nv more vertices and nt more triangles keep the numbers within
** 32 bits (else b->failed); 0 after an earlier failure too. */
static int builder_room(builder *b, uint64_t nv, uint64_t nt)
{
    if (b->failed) return 0;
    if (b->vertices + nv > UINT32_MAX || b->triangles + nt > UINT32_MAX) {
        b->failed = brt_fail(b->err, BRT_EARG, "%s: scale %g needs more than 2^32 - 1 vertices "
                             "or triangles", b->name, b->scale);
        return 0;
    }
    return 1;
}

/*
** Adds one surface.  Vertex (ring i, segment j) is base + i*segs + j, the
** poles follow the rings.  Each quad (i,j)-(i,j+1)-(i+1,j+1)-(i+1,j) is
** split along the same diagonal, and the pole fans run against the ring
** edges they share, so every surface is consistently oriented: a closed
** one has each edge once in each direction.
**
** The rings are made one after another, band by band: only the first
** ring (a band or fan may come back to it), the two of the current band
** and the poles are held, so a terrain grid of millions of triangles costs
** three rows of vertices.  Vertices and triangles come out in the order of
** the indexed arrays: all rings, then the poles; all bands, then the fan
** of the start pole, then that of the end pole.
*/
static void emit_surface(builder *b, const grid *g, surface_fn fn,
                         const void *shape, const xform *x)
{
    surface s;
    uint64_t base = b->vertices, nv = grid_vertices(g), nt = grid_triangles(g);
    uint32_t bands = (g->flags & WRAP_V) ? g->rings : g->rings - 1, i, k;
    float pole_xyz[2][3];
    ring first, lo, hi, poles[2];
    double p[3];

    if (!builder_room(b, nv, nt)) return;
    b->vertices += nv;
    if (b->out == OUT_COUNT) {
        b->triangles += nt;
        return;
    }
    if (!reserve_rings(b, g->segs)) return;
    s.g = g;
    s.fn = fn;
    s.shape = shape;
    s.x = x;
    for (k = 0; k < grid_poles(g); k++) {
        fn(shape, 0, (k == 0 && (g->flags & POLE_START)) ? 0 : 1, p);
        put_vertex(pole_xyz[k], x, p);
        poles[k].xyz = pole_xyz[k];
        poles[k].first = base + (uint64_t)g->segs * g->rings + k;
    }
    first.xyz = b->rings[0];
    first.first = base;
    surface_ring(&s, 0, b->rings[0]);
    put_vertices(b, first.xyz, g->segs);
    lo = first;
    for (i = 0; i < bands && !b->failed; i++) {
        uint32_t next = (i + 1) % g->rings;
        hi.first = base + (uint64_t)next * g->segs;
        if (next == 0) {
            hi.xyz = first.xyz;
        } else {   /* the buffer lo does not use */
            float *free_ring = b->rings[lo.xyz == b->rings[1] ? 2 : 1];
            surface_ring(&s, next, free_ring);
            put_vertices(b, free_ring, g->segs);
            hi.xyz = free_ring;
        }
        put_band(b, &s, &lo, &hi);
        if (next != 0) lo = hi;
    }
    put_vertices(b, pole_xyz[0], grid_poles(g));
    /* lo is now the last ring (with WRAP_V the last band ends on ring 0) */
    if (g->flags & POLE_START) put_fan(b, g->segs, &poles[0], &first, 1);
    if (g->flags & POLE_END) put_fan(b, g->segs, &poles[grid_poles(g) - 1], &lo, 0);
}

/* Starts a part of material m at the next triangle (instanced scenes'
** colours); nothing unless the builder logs parts, or when m goes on. */
static void mark_material(builder *b, ex_material m)
{
    part_log *log = b->parts;
    if (!log || (log->count > 0 && log->material[log->count - 1] == m)) return;
    if (log->count == MAX_PARTS) return;   /* never: no mesh has that many parts */
    log->start[log->count] = b->triangles;
    log->material[log->count++] = (unsigned char)m;
}

/* One lone triangle with three vertices of its own (a leaf, a needle):
** it shares no vertex, so foliage is separate triangles with empty space
** between them, as in the paper's scenes. */
static void emit_triangle(builder *b, const double p[9], const xform *x)
{
    float xyz[9];
    ring r;
    int k;
    if (!builder_room(b, 3, 1)) return;
    b->vertices += 3;
    if (b->out == OUT_COUNT) {
        b->triangles++;
        return;
    }
    for (k = 0; k < 3; k++) put_vertex(xyz + 3 * k, x, p + 3 * k);
    r.xyz = xyz;
    r.first = b->vertices - 3;
    put_vertices(b, xyz, 3);
    put_triangle(b, ring_corner(&r, 0), ring_corner(&r, 1), ring_corner(&r, 2));
}

/* ===================================================================== */
/* Shapes                                                                */
/* ===================================================================== */

/* ---- lathe: a surface of revolution about local y, from y = 0 up ---- */

enum { LATHE_ELLIPSOID, LATHE_SPIKE, LATHE_CAPPED };

typedef struct lathe {
    int profile;
    double radius, height;
    double taper;          /* CAPPED: top radius is radius * (1 - taper) */
    double bend;           /* the axis curves to x = bend * height at the top */
    double rough;          /* radial noise amplitude (rocks), 0 for smooth */
    double lobes[3][4];    /* rough: unit direction and phase of each lobe */
} lathe;

/* Radius and height at v.  CAPPED spends the first and last fifth of v on
** flat caps, so a grid of 4 rings gives a cylinder with sharp rims. */
static void lathe_profile(const lathe *l, double v, double *r, double *y)
{
    double side, cap;
    switch (l->profile) {
    case LATHE_ELLIPSOID:
        *y = l->height * 0.5 * (1 - cos(PI * v));
        *r = l->radius * sin(PI * v);
        break;
    case LATHE_SPIKE:   /* a swelling spike; r and y are linear in v at
                        ** the tip, so the last ring never shrinks to
                        ** nothing under float rounding at high res */
        *y = l->height * v;
        *r = l->radius * 1.4 * sin(PI * v) * (1 - 0.5 * v);
        break;
    default:
        side = v < 0.2 ? 0 : v > 0.8 ? 1 : (v - 0.2) / 0.6;
        cap = v < 0.2 ? v / 0.2 : v > 0.8 ? (1 - v) / 0.2 : 1;
        *y = l->height * side;
        *r = l->radius * (1 - l->taper * side) * cap;
        break;
    }
}

static void lathe_point(const void *shape, double u, double v, double p[3])
{
    const lathe *l = shape;
    double r, y, a = -2 * PI * u, t;   /* -u: outward normals */
    lathe_profile(l, v, &r, &y);
    p[0] = r * cos(a);
    p[1] = y;
    p[2] = r * sin(a);
    if (l->rough > 0) {
        /* Radial noise about the centre: a sum of three plane waves over
        ** the direction, smooth and cheap, never shrinking r below 0. */
        double d[3], noise = 0, scale;
        int k;
        d[0] = p[0];
        d[1] = y - 0.5 * l->height;
        d[2] = p[2];
        for (k = 0; k < 3; k++)
            noise += cos(4 * (d[0] * l->lobes[k][0] + d[1] * l->lobes[k][1] + d[2] * l->lobes[k][2])
                         / l->radius + l->lobes[k][3]) / 3;
        scale = 1 + l->rough * noise;
        p[0] *= scale;
        p[1] = 0.5 * l->height + d[1] * scale;
        p[2] *= scale;
    }
    t = y / l->height;
    p[0] += l->bend * l->height * t * t;
}

/* ---- tube: a thick curve along an elliptic arc in the local xy plane -- */

typedef struct tube {
    double ax, ay;            /* semi-axes of the centre line */
    double a0, a1;            /* arc angles (a full turn: a ring, WRAP_V) */
    double width, depth;      /* cross-section half sizes: in-plane, along z */
    double boxiness;          /* superellipse exponent: 1 round, < 1 boxy */
    int capped;               /* the section shrinks to a point at both ends */
    double scallops, swell;   /* the section swells `scallops` times */
} tube;

static double signed_pow(double x, double e)
{
    return x < 0 ? -pow(-x, e) : pow(x, e);
}

static void tube_point(const void *shape, double u, double v, double p[3])
{
    const tube *t = shape;
    double theta = t->a0 + (t->a1 - t->a0) * v, phi = -2 * PI * u;  /* -u: outward */
    double n[3], f = 1 + t->swell * cos(t->scallops * theta);
    double cx = signed_pow(cos(phi), t->boxiness), cz = signed_pow(sin(phi), t->boxiness);
    n[0] = t->ay * cos(theta);
    n[1] = t->ax * sin(theta);
    n[2] = 0;
    ex_normalize3(n);
    if (t->capped) f *= pow(sin(PI * v), 0.3);
    p[0] = t->ax * cos(theta) + n[0] * t->width * f * cx;
    p[1] = t->ay * sin(theta) + n[1] * t->width * f * cx;
    p[2] = t->depth * f * cz;
}

/* ---- card: a flat, tapering, drooping strip (leaf, blade, frond) ---- */

typedef struct card {
    double width, length;
    double taper;   /* the tip is (1 - taper) as wide as the base; < 1 */
    double bend;    /* the tip droops bend * length along local z */
} card;

static void card_point(const void *shape, double u, double v, double p[3])
{
    const card *c = shape;
    p[0] = (u - 0.5) * c->width * (1 - c->taper * v);
    p[1] = c->length * v;
    p[2] = c->bend * c->length * v * v;
}

static const grid blade_grid = {2, 4, 0};     /* 6 triangles */
static const grid frond_grid = {2, 6, 0};     /* 10 triangles */

/* ---- terrain: value noise, sampled on square or radial grids ---- */

/* A lattice value in [-1, 1] from a hash of its integer coordinates. */
static double lattice(uint64_t seed, int64_t ix, int64_t iz)
{
    uint64_t state = seed ^ ((uint64_t)ix * 0x9E3779B97F4A7C15ull)
                          ^ ((uint64_t)iz * 0xC2B2AE3D27D4EB4Full);
    return 2.0 * brt_random_float(&state) - 1.0;
}

/* Value noise with smoothstep interpolation, then octaves of it (fBm). */
static double value_noise(uint64_t seed, double x, double z)
{
    double fx = floor(x), fz = floor(z), tx = x - fx, tz = z - fz;
    int64_t ix = (int64_t)fx, iz = (int64_t)fz;
    double a = lattice(seed, ix, iz), b = lattice(seed, ix + 1, iz);
    double c = lattice(seed, ix, iz + 1), d = lattice(seed, ix + 1, iz + 1);
    tx = tx * tx * (3 - 2 * tx);
    tz = tz * tz * (3 - 2 * tz);
    return (a + (b - a) * tx) * (1 - tz) + (c + (d - c) * tx) * tz;
}

static double fbm(uint64_t seed, double x, double z, int octaves)
{
    double sum = 0, amplitude = 1;
    int k;
    for (k = 0; k < octaves; k++) {
        sum += amplitude * value_noise(seed + (uint64_t)k, x, z);
        x *= 2.03;   /* not exactly 2, so octaves do not line up */
        z *= 2.03;
        amplitude *= 0.5;
    }
    return sum;
}

/* Rolling hills plus mountain ranges on the landscape (y = 0 when flat). */
typedef struct terrain {
    uint64_t seed;
    double hills, mountains;    /* amplitudes in metres (0: flat) */
} terrain;

static double terrain_height(const terrain *t, double x, double z)
{
    double ridge;
    if (t->hills == 0 && t->mountains == 0) return 0;
    ridge = fbm(t->seed + 100, x / 2000, z / 2000, 3);
    return t->hills * fbm(t->seed, x / 250, z / 250, 5) + t->mountains * (ridge > 0 ? ridge * ridge : 0);
}

typedef struct patch {          /* a square [x0, x0+size] x [z0, z0+size] */
    double x0, z0, size;
    const terrain *ground;
} patch;

static void patch_point(const void *shape, double u, double v, double p[3])
{
    const patch *s = shape;
    p[0] = s->x0 + v * s->size;   /* u along z, v along x: normals up */
    p[2] = s->z0 + u * s->size;
    p[1] = terrain_height(s->ground, p[0], p[2]);
}

/* An island: a dome whose rim lies under the sea, with a noisy coast. */
typedef struct island {
    double cx, cz, radius, peak;
    uint64_t seed;
    double v_rim;               /* v of the dome's last ring: the rim */
    uint32_t under_rings;       /* R: the underside's rings below the rim */
} island;

#define ISLAND_RIM 1.35   /* the grid reaches this many radii out */

static double island_height(const island *s, double x, double z)
{
    double dx = (x - s->cx) / s->radius, dz = (z - s->cz) / s->radius;
    double d2 = dx * dx + dz * dz;
    return s->peak * (1 - d2) + 0.35 * s->peak * fbm(s->seed, x / 60, z / 60, 4) * (d2 < 1 ? 1 : 1 / d2);
}

/* The land mass is closed (inner proxies, svdag.c): the dome's rings run
** out to the rim (v = v_rim), and the grid goes on below it, down and in:
** underside ring j = 1 .. R at radius (1 - j/(R+1)) times the rim's, its
** height going linearly from the rim's height to ISLAND_BASE peaks below
** the sea, and the end pole at v = 1 under the peak at that depth.  The
** rim ring itself is the dome's (v = v_rim gives r = the rim's radius by
** the dome's formula), so the underside starts on the very same vertices.
**
** Why rings and not one cone from the rim to the pole: a batching point's
** box holds all of its triangles, and a cone's triangles each span the
** island's radius, so the points holding them would cover the island and
** every ray near it would visit them.  With ISLAND_UNDER_STEPS dome ring
** steps per underside ring step, the underside's triangles stay local. */
#define ISLAND_BASE 1.5
#define ISLAND_UNDER_STEPS 2

/* R for a dome of `rings` rings (pole not counted). */
static uint32_t island_under_rings(uint32_t rings)
{
    return rings / ISLAND_UNDER_STEPS < 1 ? 1 : rings / ISLAND_UNDER_STEPS;
}

static void island_point(const void *shape, double u, double v, double p[3])
{
    const island *s = shape;
    double a = 2 * PI * u, rim = ISLAND_RIM * s->radius, r, t, rim_y;
    if (v <= s->v_rim) {   /* the dome */
        r = v / s->v_rim * rim;   /* +u: normals up */
        p[0] = s->cx + r * cos(a);
        p[2] = s->cz + r * sin(a);
        p[1] = island_height(s, p[0], p[2]);
        return;
    }
    /* the underside: t = j/(R+1), exactly 1 at the pole (v = 1) */
    t = (v - s->v_rim) / (1 - s->v_rim);
    rim_y = island_height(s, s->cx + rim * cos(a), s->cz + rim * sin(a));
    r = (1 - t) * rim;
    p[0] = s->cx + r * cos(a);
    p[2] = s->cz + r * sin(a);
    p[1] = (1 - t) * rim_y - t * ISLAND_BASE * s->peak;
}

/* ===================================================================== */
/* Composite instances: trees, rocks, plants                             */
/* ===================================================================== */

static const double up[3] = {0, 1, 0};
static const xform world = {{{1, 0, 0}, {0, 1, 0}, {0, 0, 1}}, {0, 0, 0}};   /* identity */

static lathe capped_lathe(double radius, double height, double taper, double bend)
{
    lathe l;
    memset(&l, 0, sizeof l);
    l.profile = LATHE_CAPPED;
    l.radius = radius;
    l.height = height;
    l.taper = taper;
    l.bend = bend;
    return l;
}

static lathe ellipsoid(double radius, double height)
{
    lathe l;
    memset(&l, 0, sizeof l);
    l.profile = LATHE_ELLIPSOID;
    l.radius = radius;
    l.height = height;
    return l;
}

/* ===================================================================== */
/* The crown                                                             */
/* ===================================================================== */
/*
** A band of radius 1 (y from 0 to 0.32) with scalloped, boxy section; four
** arches crossing over the top; spikes between the arches' feet; gems on
** the band; pearls on the band's rims and along the arches; an orb and a
** cross on top.  Every part is a closed grid, so the whole is closed.
** Budget shares: band 30 %, arches 15 %, spikes 10 %, gems 15 %, pearls
** 25 %, orb and cross 5 %.  The number of pearls grows with sqrt(scale),
** everything else gets finer.
*/

#define CROWN_ARCHES 4
#define CROWN_SPIKES 8
#define CROWN_GEMS 16
#define ARCH_CENTRE_Y 0.28
#define ARCH_HEIGHT 0.75

static void crown_band(builder *b, double budget, uint64_t *rng)
{
    static const double x_axis[3] = {1, 0, 0}, y_axis[3] = {0, 0, -1}, at[3] = {0, 0.16, 0};
    tube band;
    grid g = grid_for_budget(budget, 1 / 7.5, WRAP_U | WRAP_V);
    xform x = xform_frame(x_axis, y_axis, 1, at);
    band.ax = band.ay = 1;
    band.a0 = rnd(rng, 0, 1);
    band.a1 = band.a0 + 2 * PI;
    band.width = 0.05;
    band.depth = 0.16;
    band.boxiness = 0.4;
    band.capped = 0;
    band.scallops = 2 * CROWN_GEMS;
    band.swell = 0.12;
    emit_surface(b, &g, tube_point, &band, &x);
}

/* The centre line of arch k at angle theta (0..pi), in world space. */
static void arch_point(int k, double theta, double p[3])
{
    double phi = PI * k / CROWN_ARCHES;
    p[0] = cos(theta) * cos(phi);
    p[1] = ARCH_CENTRE_Y + ARCH_HEIGHT * sin(theta);
    p[2] = cos(theta) * sin(phi);
}

static void crown_arches(builder *b, double budget)
{
    static const double at[3] = {0, ARCH_CENTRE_Y, 0};
    grid g = grid_for_budget(budget / CROWN_ARCHES, 1 / 12.5, WRAP_U | POLE_START | POLE_END);
    tube arch;
    int k;
    arch.ax = 1;
    arch.ay = ARCH_HEIGHT;
    arch.a0 = 0;
    arch.a1 = PI;
    arch.width = arch.depth = 0.035;
    arch.boxiness = 1;
    arch.capped = 1;
    arch.scallops = 0;
    arch.swell = 0;
    for (k = 0; k < CROWN_ARCHES; k++) {
        double phi = PI * k / CROWN_ARCHES;
        double x_axis[3], y_axis[3] = {0, 1, 0};
        xform x;
        x_axis[0] = cos(phi);
        x_axis[1] = 0;
        x_axis[2] = sin(phi);
        x = xform_frame(x_axis, y_axis, 1, at);
        emit_surface(b, &g, tube_point, &arch, &x);
    }
}

static void crown_spikes(builder *b, double budget, uint64_t *rng)
{
    grid g = grid_for_budget(budget / CROWN_SPIKES, 1.0, SPHERE_LIKE);
    int k;
    for (k = 0; k < CROWN_SPIKES; k++) {
        double a = 2 * PI * (k + 0.5) / CROWN_SPIKES, at[3], axis[3];
        lathe spike;
        xform x;
        memset(&spike, 0, sizeof spike);
        spike.profile = LATHE_SPIKE;
        spike.radius = 0.05;
        spike.height = rnd(rng, 0.3, 0.4);
        at[0] = cos(a);
        at[1] = 0.24;
        at[2] = sin(a);
        axis[0] = 0.15 * cos(a);
        axis[1] = 1;
        axis[2] = 0.15 * sin(a);
        x = xform_along(axis, 0, 1, at);
        emit_surface(b, &g, lathe_point, &spike, &x);
    }
}

/* An upright sphere of radius r centred at c. */
static void emit_ball(builder *b, const grid *g, double r, const double c[3])
{
    lathe ball = ellipsoid(r, 2 * r);
    double at[3];
    xform x;
    at[0] = c[0];
    at[1] = c[1] - r;
    at[2] = c[2];
    x = xform_along(up, 0, 1, at);
    emit_surface(b, g, lathe_point, &ball, &x);
}

static void crown_gems(builder *b, double budget, uint64_t *rng)
{
    grid g = grid_for_budget(budget / CROWN_GEMS, 2.0, SPHERE_LIKE);
    int k;
    for (k = 0; k < CROWN_GEMS; k++) {
        double a = 2 * PI * k / CROWN_GEMS, radial[3], at[3];
        lathe gem = ellipsoid(rnd(rng, 0.035, 0.05), 0.05);
        xform x;
        radial[0] = cos(a);
        radial[1] = 0;
        radial[2] = sin(a);
        at[0] = 1.02 * cos(a);
        at[1] = 0.16;
        at[2] = 1.02 * sin(a);
        x = xform_along(radial, 0, 1, at);
        emit_surface(b, &g, lathe_point, &gem, &x);
    }
}

/* Pearls: a quarter on each rim of the band, half along the arches. */
static void crown_pearls(builder *b, double budget, double scale, uint64_t *rng)
{
    uint32_t count = (uint32_t)(200 * sqrt(scale)), per_rim, per_arch, i;
    grid g;
    int rim, k;
    if (count < 40) count = 40;
    per_rim = count / 4;
    per_arch = (count - 2 * per_rim) / CROWN_ARCHES;
    g = grid_for_budget(budget / (2 * per_rim + CROWN_ARCHES * per_arch), 2.0, SPHERE_LIKE);
    for (rim = 0; rim < 2; rim++) {
        double r = fmin(0.03, 0.45 * 2 * PI / per_rim);
        for (i = 0; i < per_rim; i++) {
            double a = 2 * PI * (i + 0.5) / per_rim, c[3];
            c[0] = 1.05 * cos(a);
            c[1] = rim ? 0.31 : 0.01;
            c[2] = 1.05 * sin(a);
            emit_ball(b, &g, r * rnd(rng, 0.9, 1.1), c);
        }
    }
    for (k = 0; k < CROWN_ARCHES; k++) {
        double r = fmin(0.045, 0.45 * 2.6 / per_arch);
        for (i = 0; i < per_arch; i++) {
            double c[3];
            arch_point(k, 0.15 + (PI - 0.3) * (i + 0.5) / per_arch, c);
            emit_ball(b, &g, r * rnd(rng, 0.9, 1.1), c);
        }
    }
}

static void crown_top(builder *b, double budget)
{
    static const double side[3] = {1, 0, 0};
    double apex = ARCH_CENTRE_Y + ARCH_HEIGHT, orb_c[3] = {0, 0, 0}, bar_at[3] = {0, 0, 0};
    grid g = grid_for_budget(budget / 3, 2.0, SPHERE_LIKE);
    lathe bar = ellipsoid(0.025, 0.32);
    xform x;
    orb_c[1] = apex + 0.08;
    emit_ball(b, &g, 0.11, orb_c);
    bar_at[1] = apex + 0.15;
    x = xform_along(up, 0, 1, bar_at);
    emit_surface(b, &g, lathe_point, &bar, &x);
    bar.height = 0.22;
    bar_at[0] = -0.11;
    bar_at[1] = apex + 0.36;
    x = xform_along(side, 0, 1, bar_at);
    emit_surface(b, &g, lathe_point, &bar, &x);
}

static void build_crown(builder *b, double scale, uint64_t seed)
{
    double budget = TRIANGLES_PER_SCALE * scale;
    uint64_t rng = seed;
    crown_band(b, 0.30 * budget, &rng);
    crown_arches(b, 0.15 * budget);
    crown_spikes(b, 0.10 * budget, &rng);
    crown_gems(b, 0.15 * budget, &rng);
    crown_pearls(b, 0.25 * budget, scale, &rng);
    crown_top(b, 0.05 * budget);
}

/* ===================================================================== */
/* The landscape                                                         */
/* ===================================================================== */
/*
** A square of 600 * sqrt(scale) metres (so instance density stays the
** same at every scale; mountain ranges 2 km across appear from scale 10
** on), 20 % of the budget in the terrain grid, 70 % in trees (forests of
** 40, each with its own mix of conifers and leafy trees), 10 % in rocks
** (groups of up to 6).
*/

#define LANDSCAPE_SIDE 600.0   /* metres at scale 1 */

/*
** The terrain closed below (inner proxies, svdag.c): a skirt around the
** patch down to a floor, and the floor, as one surface: u runs around the
** patch's border vertex by vertex (WRAP_U), ring 0 is the border itself --
** the very points patch_point gives the terrain grid (same u, v, same
** function, so equal bits and shared edges) -- ring 1 is the border
** dropped to the floor, rings 2 .. R+1 the dropped border scaled toward
** the floor's centre by 1 - j/(R+1) (j = ring - 1), and the end pole the
** centre itself.
**
** Why rings and not one fan from the border to the centre: a batching
** point's box holds all of its triangles, and a fan's triangles each span
** half the scene, so the points holding them would be as big as the scene
** and every ray would visit them.  With a ring step of FLOOR_RING_CELLS
** terrain cells, a floor triangle is about that long radially and at most
** one cell wide (each ring has the border's vertex count).
*/
#define FLOOR_RING_CELLS 3

typedef struct skirt {
    const patch *land;
    const grid *top;            /* the terrain's grid */
    double floor;
    uint32_t floor_rings;       /* R: the rings on the floor inside the dropped border */
} skirt;

/* R for a terrain grid: the floor's half width, (top->segs - 1) / 2 cells,
** in steps of about FLOOR_RING_CELLS cells. */
static uint32_t skirt_floor_rings(const grid *top)
{
    uint32_t steps = (top->segs - 1) / (2 * FLOOR_RING_CELLS);
    return steps < 2 ? 1 : steps - 1;
}

static uint32_t skirt_segments(const grid *top)
{
    return 2 * (top->segs - 1) + 2 * (top->rings - 1);
}

/* Border vertex k of the terrain grid, counterclockwise from (0, 0). */
static void skirt_border(const skirt *s, uint32_t k, double p[3])
{
    uint32_t sides[4], seg, row;
    double du = 1.0 / (s->top->segs - 1);
    sides[0] = sides[2] = s->top->segs - 1;
    sides[1] = sides[3] = s->top->rings - 1;
    if (k < sides[0]) { seg = k; row = 0; }
    else if ((k -= sides[0]) < sides[1]) { seg = sides[0]; row = k; }
    else if ((k -= sides[1]) < sides[2]) { seg = sides[0] - k; row = sides[1]; }
    else { k -= sides[2]; seg = 0; row = sides[1] - k; }
    patch_point(s->land, seg * du, grid_v(s->top, row), p);
}

/* v = level / (R + 2) (grid_v with an end pole, level = the ring's
** number); the rounding recovers the level, as it recovers the border
** vertex from u. */
static void skirt_point(const void *shape, double u, double v, double p[3])
{
    const skirt *s = shape;
    double cx = s->land->x0 + 0.5 * s->land->size, cz = s->land->z0 + 0.5 * s->land->size;
    uint32_t level = (uint32_t)(v * (s->floor_rings + 2) + 0.5);
    double keep = 1 - (level < 2 ? 0.0 : (double)(level - 1) / (s->floor_rings + 1));
    skirt_border(s, (uint32_t)(u * skirt_segments(s->top) + 0.5), p);
    if (level == 0) return;   /* the terrain's own border: not a bit changed */
    p[0] = cx + keep * (p[0] - cx);
    p[1] = s->floor;
    p[2] = cz + keep * (p[2] - cz);
}

/* Hills and mountain ranges under a square of the given side centred on
** the origin; draws the terrain's seed from rng. */
static void landscape_terrain(uint64_t *rng, double side, terrain *ground, patch *land)
{
    ground->seed = brt_random_u64(rng);
    ground->hills = 20;
    ground->mountains = 250;
    land->x0 = land->z0 = -0.5 * side;
    land->size = side;
    land->ground = ground;
}

/* The terrain grid g over land, then its skirt and floor (closed below). */
static void emit_ground(builder *b, const patch *land, const grid *g)
{
    skirt below;
    grid around;
    mark_material(b, EX_MAT_TERRAIN);
    emit_surface(b, g, patch_point, land, &world);
    mark_material(b, EX_MAT_ROCK);
    below.land = land;
    below.top = g;
    below.floor = -2 * land->ground->hills - 1;   /* fbm > -2: under every point */
    below.floor_rings = skirt_floor_rings(g);
    around.segs = skirt_segments(g);
    around.rings = 2 + below.floor_rings;
    around.flags = WRAP_U | POLE_END;
    emit_surface(b, &around, skirt_point, &below, &world);
}

/* A square terrain grid of about `triangles` triangles. */
static grid terrain_grid(double triangles)
{
    grid g;
    g.segs = g.rings = (uint32_t)sqrt(triangles / 2) + 2;
    g.flags = 0;
    return g;
}

/* ===================================================================== */
/* The islands                                                           */
/* ===================================================================== */
/*
** 3 * sqrt(scale) islands (at least 3) of radius 60-110 m, in a sea of
** two triangles; their radial grids share the world's budget
** (island_setup), plants stand on dry land (island_base).
*/

#define ISLAND_SPACING 320.0
#define DRY_LAND 1.5          /* plants grow this far above the sea */

static void emit_sea(builder *b, double half_side)
{
    static const terrain flat = {0, 0, 0};
    static const grid two_triangles = {2, 2, 0};
    patch sea;
    sea.x0 = sea.z0 = -half_side;
    sea.size = 2 * half_side;
    sea.ground = &flat;
    emit_surface(b, &two_triangles, patch_point, &sea, &world);
}

/* Places island i away from the earlier ones (a few tries, then anywhere). */
static void place_island(uint64_t *rng, island *all, uint32_t i, double half_side)
{
    int attempt;
    all[i].radius = rnd(rng, 60, 110);
    all[i].peak = rnd(rng, 15, 35);
    all[i].seed = brt_random_u64(rng);
    for (attempt = 0; attempt < 50; attempt++) {
        uint32_t j;
        all[i].cx = rnd(rng, -half_side, half_side);
        all[i].cz = rnd(rng, -half_side, half_side);
        for (j = 0; j < i; j++) {
            double dx = all[i].cx - all[j].cx, dz = all[i].cz - all[j].cz;
            double gap = 1.2 * (all[i].radius + all[j].radius);
            if (dx * dx + dz * dz < gap * gap) break;
        }
        if (j == i) return;
    }
}

/* A random spot on dry land of the island, or 0 after a few misses. */
static int dry_spot(uint64_t *rng, const island *s, double at[3])
{
    int attempt;
    for (attempt = 0; attempt < 8; attempt++) {
        double a = rnd(rng, 0, 2 * PI), r = 1.2 * s->radius * sqrt(rnd(rng, 0, 1));
        at[0] = s->cx + r * cos(a);
        at[2] = s->cz + r * sin(a);
        at[1] = island_height(s, at[0], at[2]);
        if (at[1] > DRY_LAND) return 1;
    }
    return 0;
}

/* The grid of an island of about `triangles` triangles: a dome, then the
** underside's rings (sets the island's under_rings and v_rim). */
static grid island_grid(island *s, double triangles)
{
    grid g = grid_for_budget(triangles, 2 * PI, SPHERE_LIKE);
    uint32_t dome_rings = g.rings;
    s->under_rings = island_under_rings(dome_rings);
    g.rings += s->under_rings;
    s->v_rim = grid_v(&g, dome_rings - 1);
    return g;
}

/* 3 * sqrt(scale) islands, at least 3. */
static uint32_t island_count(double scale)
{
    uint32_t count = (uint32_t)(3 * sqrt(scale) + 0.5);
    return count < 3 ? 3 : count;
}

static double island_half_side(uint32_t count)
{
    return 0.5 * ISLAND_SPACING * sqrt((double)count);
}

/* ===================================================================== */
/* Public entry points                                                   */
/* ===================================================================== */

static const char *const scene_names[] = {"crown", "landscape", "island", NULL};

const char *const *ex_scene_names(void)
{
    return scene_names;
}

static int scene_index(const char *name)
{
    int i;
    for (i = 0; name && scene_names[i]; i++)
        if (strcmp(name, scene_names[i]) == 0) return i;
    return -1;
}

int ex_scene_is_builtin(const char *name)
{
    return scene_index(name) >= 0;
}

/* The batches of the builder's output; 0 (and b->failed) when they
** cannot be allocated. */
static int builder_start(builder *b, const char *name, double scale)
{
    b->name = name;
    b->scale = scale;
    if (b->out == OUT_INDEXED) b->vertex_batch = malloc(12 * (size_t)BATCH);
    if (b->out != OUT_COUNT)
        b->triangle_batch = malloc((b->out == OUT_INDEXED ? 12 : 36) * (size_t)BATCH);
    if ((b->out == OUT_INDEXED && !b->vertex_batch) || (b->out != OUT_COUNT && !b->triangle_batch)) {
        fail_out_of_memory(b);
        return 0;
    }
    return 1;
}

/* Hands on what is left in the batches, frees them; the first failure. */
static brt_result builder_finish(builder *b)
{
    flush_vertices(b);
    flush_triangles(b);
    free(b->vertex_batch);
    free(b->triangle_batch);
    free(b->rings[0]);
    free(b->rings[1]);
    free(b->rings[2]);
    return b->failed;
}

static brt_result bake(builder *b, const ex_scene_recipe *recipe);

/* Checks the recipe, then makes its scene into the builder's output: the
** crown with its builder, the landscape and the island baked (bake). */
static brt_result run_builder(builder *b, const ex_scene_recipe *recipe)
{
    int index = scene_index(recipe->name);
    if (index < 0)
        return brt_fail(b->err, BRT_EARG, "unknown scene '%s' (built-in: crown, landscape, island)",
                        recipe->name ? recipe->name : "(null)");
    if (!(recipe->scale > 0 && recipe->scale <= EX_SCENE_MAX_SCALE))
        return brt_fail(b->err, BRT_EARG, "%s: scale %g outside (0, %g]", recipe->name,
                        recipe->scale, EX_SCENE_MAX_SCALE);
    if (index > 0) return bake(b, recipe);
    if (builder_start(b, recipe->name, recipe->scale)) build_crown(b, recipe->scale, recipe->seed);
    return builder_finish(b);
}

static void builder_init(builder *b, enum output out, brt_error *err)
{
    memset(b, 0, sizeof *b);
    b->out = out;
    b->err = err;
}

brt_result ex_scene_count(const ex_scene_recipe *recipe, uint64_t *vertices, uint64_t *triangles,
                          brt_error *err)
{
    builder b;
    brt_result r;
    builder_init(&b, OUT_COUNT, err);
    r = run_builder(&b, recipe);
    *vertices = r == BRT_OK ? b.vertices : 0;
    *triangles = r == BRT_OK ? b.triangles : 0;
    return r;
}

brt_result ex_scene_write(const ex_scene_recipe *recipe, const ex_mesh_sink *sink, brt_error *err)
{
    builder b;
    builder_init(&b, OUT_INDEXED, err);
    b.sink = *sink;
    return run_builder(&b, recipe);
}

brt_result ex_scene_stream(const ex_scene_recipe *recipe, brt_triangle_fn emit, void *emit_user,
                           brt_error *err)
{
    builder b;
    builder_init(&b, OUT_TRIANGLES, err);
    b.emit = emit;
    b.emit_user = emit_user;
    return run_builder(&b, recipe);
}

static brt_result source_run(const void *user, brt_triangle_fn emit, void *emit_user,
                             brt_error *err)
{
    return ex_scene_stream(user, emit, emit_user, err);
}

void ex_scene_source(const ex_scene_recipe *recipe, brt_triangle_source *source)
{
    source->run = source_run;
    source->user = recipe;
}

uint64_t ex_scene_stamp(const ex_scene_recipe *recipe)
{
    char text[256];
    int n = snprintf(text, sizeof text, "batchrt built-in scene %s, scale %.17g, seed %llu, "
                     "generator %d", recipe->name, recipe->scale,
                     (unsigned long long)recipe->seed, EX_SCENE_GENERATOR_VERSION);
    return brt_checksum64(text, n < (int)sizeof text ? (size_t)n : sizeof text - 1);
}

/* ---- the collector: the whole mesh in two growing arrays ---- */

typedef struct collector {
    void *positions, *indices;     /* 12 bytes per vertex, 12 per triangle */
    size_t vertex_cap, triangle_cap;
    uint32_t vertex_count, triangle_count;
    const char *name;
    double scale;
} collector;

/* Grows one array unless it has room for `need` (brt_grow); need never
** passes 2^32 - 1 (emit_surface refuses more). */
static int grow(void **array, size_t *cap, uint64_t need)
{
    void *bigger = brt_grow(*array, cap, (size_t)need, 12);
    if (bigger) *array = bigger;
    return bigger != NULL;
}

/* Appends n items of 12 bytes (vertices or index triples) to an array. */
static brt_result append(const collector *c, void **array, size_t *cap, uint32_t *count,
                         const void *items, uint32_t n, brt_error *err)
{
    if (!grow(array, cap, (uint64_t)*count + n)) {
        out_of_memory(err, c->name, c->scale);
        return BRT_ENOMEM;
    }
    memcpy((unsigned char *)*array + 12 * (size_t)*count, items, 12 * (size_t)n);
    *count += n;
    return BRT_OK;
}

static brt_result collect_vertices(void *user, const float *xyz, uint32_t count, brt_error *err)
{
    collector *c = user;
    return append(c, &c->positions, &c->vertex_cap, &c->vertex_count, xyz, count, err);
}

static brt_result collect_triangles(void *user, const uint32_t *abc, uint32_t count,
                                    brt_error *err)
{
    collector *c = user;
    return append(c, &c->indices, &c->triangle_cap, &c->triangle_count, abc, count, err);
}

/* A collector of exactly the given size (the arrays never grow) and its
** sink; BRT_ENOMEM when the arrays cannot be allocated. */
static brt_result collector_open(collector *c, uint64_t vertices, uint64_t triangles,
                                 ex_mesh_sink *sink, brt_error *err)
{
    sink->vertices = collect_vertices;
    sink->triangles = collect_triangles;
    sink->user = c;
    if (grow(&c->positions, &c->vertex_cap, vertices) && grow(&c->indices, &c->triangle_cap, triangles))
        return BRT_OK;
    out_of_memory(err, c->name, c->scale);
    return BRT_ENOMEM;
}

/* The collected mesh when r is BRT_OK; else frees the arrays. */
static brt_result collector_close(collector *c, brt_result r, brt_mesh *mesh)
{
    memset(mesh, 0, sizeof *mesh);
    if (r != BRT_OK) {
        free(c->positions);
        free(c->indices);
        return r;
    }
    mesh->positions = c->positions;
    mesh->indices = c->indices;
    mesh->vertex_count = c->vertex_count;
    mesh->triangle_count = c->triangle_count;
    return BRT_OK;
}

brt_result ex_scene_generate(const char *name, double scale, uint64_t seed,
                             brt_mesh *mesh, brt_error *err)
{
    ex_scene_recipe recipe;
    ex_mesh_sink sink;
    collector c;
    uint64_t vertices, triangles;
    brt_result r;
    memset(&c, 0, sizeof c);
    recipe.name = c.name = name;
    recipe.scale = c.scale = scale;
    recipe.seed = seed;
    /* counted first (placements only), so the arrays are allocated once */
    r = ex_scene_count(&recipe, &vertices, &triangles, err);
    if (r == BRT_OK) r = collector_open(&c, vertices, triangles, &sink, err);
    if (r == BRT_OK) r = ex_scene_write(&recipe, &sink, err);
    return collector_close(&c, r, mesh);
}

/* ===================================================================== */
/* Default views                                                         */
/* ===================================================================== */

static void set3(float out[3], double x, double y, double z)
{
    out[0] = (float)x;
    out[1] = (float)y;
    out[2] = (float)z;
}

void ex_scene_camera(const char *name, const float bmin[3], const float bmax[3],
                     float eye[3], float target[3], float *fov_degrees)
{
    double c[3], d[3], radius, span, dist;
    int k;
    for (k = 0; k < 3; k++) {
        c[k] = 0.5 * ((double)bmin[k] + bmax[k]);
        d[k] = (double)bmax[k] - bmin[k];
    }
    radius = 0.5 * sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    span = d[0] > d[2] ? d[0] : d[2];
    switch (scene_index(name)) {
    case 1:   /* landscape: just above the highest peak, over one corner,
              ** along the diagonal to the horizon -- the paper's kind of
              ** view, where rays skim over many batching points before
              ** they hit (Fig. 1); above the box, the eye is in the open */
        *fov_degrees = 60;
        set3(eye, bmin[0] + 0.02 * d[0], bmax[1] + 0.005 * span, bmin[2] + 0.02 * d[2]);
        set3(target, bmax[0], bmin[1] - 0.1 * d[1], bmax[2]);
        break;
    case 2:   /* island: from high above the sea, south of the middle */
        *fov_degrees = 50;
        set3(eye, c[0], 0.3 * span, bmin[2] + 0.05 * d[2]);
        set3(target, c[0], 0, c[2] + 0.05 * d[2]);
        break;
    default:  /* the crown and any mesh: the whole box, from +z and above */
        *fov_degrees = scene_index(name) == 0 ? 40 : 45;
        dist = 0.85 * radius / sin(0.5 * *fov_degrees * PI / 180);
        set3(target, c[0], c[1], c[2]);
        set3(eye, c[0], c[1] + 0.4 * dist, c[2] + 0.92 * dist);
        break;
    }
}

/* ===================================================================== */
/* Instanced scenes: prototypes                                          */
/* ===================================================================== */
/*
** A prototype is made by a builder like any scene, in its object space
** (y up, base point at the origin, metres), from its own random numbers;
** mark_material splits it into parts (bark first, then foliage).  Foliage
** is lone triangles (emit_triangle) in clusters, with empty space between
** them.  `detail` (d in scenes.h) multiplies the number of leaves,
** needles and leaflets, and a rock's triangles.
*/

#define ROOT 0.4   /* metres a trunk or stem reaches below the base point */

static const grid bole_grid = {10, 6, SPHERE_LIKE};   /* a trunk: 120 triangles */
static const grid twig_grid = {4, 2, SPHERE_LIKE};    /* a branch: 16 triangles */
static const grid palm_grid = {8, 12, SPHERE_LIKE};   /* a bent palm trunk */

/* A branch: from `at` along the unit direction dir for length metres. */
typedef struct limb {
    double at[3], dir[3], length;
} limb;

#define MAX_LIMBS 128

static void limb_tip(const limb *l, double tip[3])
{
    int k;
    for (k = 0; k < 3; k++) tip[k] = l->at[k] + l->length * l->dir[k];
}

static void emit_limb(builder *b, const limb *l, double radius, const grid *g)
{
    lathe shape = capped_lathe(radius, l->length, 0.7, 0);
    xform x = xform_along(l->dir, 0, 1, l->at);
    emit_surface(b, g, lathe_point, &shape, &x);
}

/* A trunk of the given radius from ROOT below the origin up to height. */
static void emit_trunk(builder *b, double radius, double height, double bend, const grid *g)
{
    const double foot[3] = {0, -ROOT, 0};
    lathe shape = capped_lathe(radius, height + ROOT, 0.8, bend);
    xform x = xform_along(up, 0, 1, foot);
    emit_surface(b, g, lathe_point, &shape, &x);
}

/* A point uniformly in the ball of radius r about c. */
static void ball_point(uint64_t *rng, const double c[3], double r, double out[3])
{
    double d[3], s;
    int k;
    do {
        for (k = 0; k < 3; k++) d[k] = rnd(rng, -1, 1);
        s = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    } while (s > 1);
    for (k = 0; k < 3; k++) out[k] = c[k] + r * d[k];
}

/* A lone leaf or needle: a triangle with its base (width across) at `at`
** and its tip `length` along dir (unit), turned at random about dir. */
static void emit_lone_leaf(builder *b, uint64_t *rng, const double at[3], const double dir[3],
                           double length, double width, const xform *x)
{
    double side[3], r[3], p[9];
    int k;
    do {   /* any direction not along dir gives the leaf's side */
        random_up(rng, PI, r);
        ex_cross3(dir, r, side);
    } while (ex_dot3(side, side) < 1e-6);
    ex_normalize3(side);
    for (k = 0; k < 3; k++) {
        p[k] = at[k] - 0.5 * width * side[k];
        p[3 + k] = at[k] + 0.5 * width * side[k];
        p[6 + k] = at[k] + length * dir[k];
    }
    emit_triangle(b, p, x);
}

/* A leaf in the ball of radius r about c, leaning upwards. */
static void emit_cluster_leaf(builder *b, uint64_t *rng, const double c[3], double r,
                              double size)
{
    double at[3], dir[3];
    ball_point(rng, c, r, at);
    random_up(rng, PI, dir);
    dir[1] += 0.4;   /* leaves lean upwards rather than down */
    if (ex_dot3(dir, dir) < 1e-6) dir[1] = 1;
    ex_normalize3(dir);
    emit_lone_leaf(b, rng, at, dir, size, 0.6 * size, &world);
}

static uint32_t detailed(double per_detail, double detail)
{
    return (uint32_t)(per_detail * detail + 0.5);
}

/* ---- conifers: whorls of drooping branches with needle clusters ---- */

typedef struct conifer_shape {
    double height, trunk_radius;
    double crown_base;            /* the first whorl, as a share of the height */
    double spread, droop;         /* the longest branch; its fall per unit length */
    uint32_t whorls, per_whorl;   /* whorls * per_whorl <= MAX_LIMBS */
    uint32_t clusters;            /* needle clusters per branch */
    double needles;               /* needles per cluster at detail 1 */
} conifer_shape;

static limb conifer_branch(uint64_t *rng, const conifer_shape *c, uint32_t w, uint32_t k)
{
    double rise = c->crown_base + (1 - c->crown_base) * (w + 0.5) / c->whorls;
    double a = 2 * PI * (k + 0.5 * (w % 2)) / c->per_whorl + rnd(rng, 0, 0.4);
    limb l;
    l.at[0] = l.at[2] = 0;
    l.at[1] = c->height * rise;
    l.dir[0] = cos(a);
    l.dir[1] = -c->droop;
    l.dir[2] = sin(a);
    ex_normalize3(l.dir);
    /* longest at the bottom of the crown, shortest at the top: a cone */
    l.length = (c->spread * (1 - rise) / (1 - c->crown_base) + 0.3) * rnd(rng, 0.85, 1.1);
    return l;
}

static void make_conifer(builder *b, uint64_t *rng, double detail, const void *shape)
{
    const conifer_shape *c = shape;
    limb limbs[MAX_LIMBS];
    uint32_t n = 0, w, k, cl, m, needles = detailed(c->needles, detail);
    mark_material(b, EX_MAT_BARK);
    emit_trunk(b, c->trunk_radius, c->height, 0, &bole_grid);
    for (w = 0; w < c->whorls; w++)
        for (k = 0; k < c->per_whorl; k++) {
            limbs[n] = conifer_branch(rng, c, w, k);
            emit_limb(b, &limbs[n++], 0.05, &twig_grid);
        }
    mark_material(b, EX_MAT_NEEDLES);
    for (k = 0; k < n; k++)
        for (cl = 0; cl < c->clusters; cl++) {
            double centre[3], along = limbs[k].length * (cl + 1) / c->clusters;
            int j;
            for (j = 0; j < 3; j++) centre[j] = limbs[k].at[j] + along * limbs[k].dir[j];
            for (m = 0; m < needles; m++) {
                double at[3], dir[3];
                ball_point(rng, centre, 0.25, at);
                random_up(rng, PI, dir);
                emit_lone_leaf(b, rng, at, dir, 0.35, 0.03, &world);
            }
        }
}

/* ---- broadleaf trees and bushes: branches, leaves at the twigs ---- */

typedef struct broadleaf_shape {
    double height, trunk_radius;
    double fork;                  /* where the branches leave the trunk (share of height) */
    double spread, rise;          /* branch length; its upward slope */
    uint32_t branches;            /* main branches, two twigs each (3 * branches + 1 <= MAX_LIMBS) */
    double leaves, leaf_size;     /* leaves at detail 1; their length */
    double cluster;               /* radius of the leaves' ball about each branch end */
} broadleaf_shape;

/* A branch from `from` turned `turn` radians about y from direction a. */
static limb branch_from(const double from[3], double a, double rise, double length)
{
    limb l;
    memcpy(l.at, from, sizeof l.at);
    l.dir[0] = cos(a);
    l.dir[1] = rise;
    l.dir[2] = sin(a);
    ex_normalize3(l.dir);
    l.length = length;
    return l;
}

/* The leader (straight up), the main branches and two twigs on each. */
static uint32_t broadleaf_limbs(uint64_t *rng, const broadleaf_shape *t, limb *limbs)
{
    double fork[3] = {0, 0, 0};
    uint32_t n = 0, k;
    int side;
    fork[1] = t->fork * t->height;
    limbs[n++] = branch_from(fork, 0, 1e6, 0.7 * (1 - t->fork) * t->height);
    for (k = 0; k < t->branches; k++) {
        double a = 2 * PI * k / t->branches + rnd(rng, 0, 0.5), mid[3];
        limb main = branch_from(fork, a, t->rise * rnd(rng, 0.8, 1.2), t->spread * rnd(rng, 0.8, 1.1));
        limbs[n++] = main;
        main.length *= 0.5;
        limb_tip(&main, mid);
        for (side = -1; side <= 1; side += 2)
            limbs[n++] = branch_from(mid, a + 0.7 * side, 1.5 * t->rise, 0.6 * t->spread);
    }
    return n;
}

static void make_broadleaf(builder *b, uint64_t *rng, double detail, const void *shape)
{
    const broadleaf_shape *t = shape;
    limb limbs[MAX_LIMBS];
    uint32_t n, k, leaves = detailed(t->leaves, detail);
    mark_material(b, EX_MAT_BARK);
    emit_trunk(b, t->trunk_radius, t->fork * t->height, 0, &bole_grid);
    n = broadleaf_limbs(rng, t, limbs);
    for (k = 0; k < n; k++) emit_limb(b, &limbs[k], 0.5 * t->trunk_radius, &twig_grid);
    mark_material(b, EX_MAT_LEAVES);
    for (k = 0; k < leaves; k++) {
        /* about the outer two thirds of a random branch: a full crown */
        limb l = limbs[(uint32_t)rnd(rng, 0, n - 1e-9)];
        double at[3];
        l.length *= rnd(rng, 0.3, 1);
        limb_tip(&l, at);
        emit_cluster_leaf(b, rng, at, t->cluster, t->leaf_size);
    }
}

/* ---- grass tufts, rocks, palms ---- */

#define TUFT_BLADES_INSTANCED 12

static void make_tuft(builder *b, uint64_t *rng, double detail, const void *shape)
{
    static const double tuft_foot[3] = {0, -0.1, 0};   /* in the ground on a slope too */
    int k;
    (void)detail;   /* a tuft is as simple at every scale */
    (void)shape;
    mark_material(b, EX_MAT_GRASS);
    for (k = 0; k < TUFT_BLADES_INSTANCED; k++) {
        double dir[3];
        card blade;
        xform x;
        blade.width = 0.03;
        blade.length = rnd(rng, 0.35, 0.7);
        blade.taper = 0.8;
        blade.bend = rnd(rng, 0.1, 0.5);
        random_up(rng, 0.6, dir);
        x = xform_along(dir, rnd(rng, 0, 2 * PI), 1, tuft_foot);
        emit_surface(b, &blade_grid, card_point, &blade, &x);
    }
}

typedef struct rock_shape {
    double radius, triangles;     /* triangles at detail 1 */
} rock_shape;

/* A rough ellipsoid sunk to a third of its height. */
static void make_rock(builder *b, uint64_t *rng, double detail, const void *shape)
{
    const rock_shape *r = shape;
    lathe rock = ellipsoid(r->radius, r->radius * rnd(rng, 0.9, 1.5));
    grid g = grid_for_budget(r->triangles * detail, 2.0, SPHERE_LIKE);
    double foot[3] = {0, 0, 0};
    xform x;
    int k;
    rock.rough = rnd(rng, 0.15, 0.3);
    for (k = 0; k < 3; k++) {
        random_up(rng, PI, rock.lobes[k]);
        rock.lobes[k][3] = rnd(rng, 0, 2 * PI);
    }
    foot[1] = -rock.height / 3;
    x = xform_along(up, 0, 1, foot);
    mark_material(b, EX_MAT_ROCK);
    emit_surface(b, &g, lathe_point, &rock, &x);
}

typedef struct palm_shape {
    double height, bend;          /* the trunk's top leans bend * its length sideways */
    double frond_length;
    uint32_t fronds;
    double leaflets;              /* per frond at detail 1 */
} palm_shape;

/* A frond: a drooping rachis (a card) with lone leaflets on both sides,
** made in the rachis's frame x. */
static void emit_frond(builder *b, uint64_t *rng, const palm_shape *p, const xform *x,
                       uint32_t leaflets)
{
    card rachis;
    uint32_t m;
    rachis.width = 0.06;
    rachis.length = p->frond_length;
    rachis.taper = 0.8;
    rachis.bend = 0.45;
    emit_surface(b, &frond_grid, card_point, &rachis, x);
    for (m = 0; m < leaflets; m++) {
        double v = 0.1 + 0.9 * (m + 0.5) / leaflets, at[3], dir[3];
        double side = m % 2 ? -1 : 1;
        card_point(&rachis, 0.5, v, at);
        dir[0] = side;
        dir[1] = 0.3;
        dir[2] = rnd(rng, 0.2, 0.6);   /* leaflets droop too */
        ex_normalize3(dir);
        emit_lone_leaf(b, rng, at, dir, 0.35 * p->frond_length * (1 - 0.6 * v), 0.06, x);
    }
}

static void make_palm(builder *b, uint64_t *rng, double detail, const void *shape)
{
    const palm_shape *p = shape;
    double top[3];
    uint32_t k, leaflets = detailed(p->leaflets, detail);
    mark_material(b, EX_MAT_BARK);
    emit_trunk(b, 0.22, p->height, p->bend, &palm_grid);
    top[0] = p->bend * (p->height + ROOT);   /* lathe_point's bend at the top */
    top[1] = p->height;
    top[2] = 0;
    mark_material(b, EX_MAT_FRONDS);
    for (k = 0; k < p->fronds; k++) {
        double a = 2 * PI * k / p->fronds + rnd(rng, 0, 0.5), dir[3];
        xform x;
        dir[0] = cos(a);
        dir[1] = rnd(rng, 0.1, 0.7);
        dir[2] = sin(a);
        x = xform_along(dir, 0, 1, top);
        emit_frond(b, rng, p, &x, leaflets);
    }
}

/* ---- the prototypes of each scene ---- */

enum { GROUP_FOREST, GROUP_MEADOW, GROUP_ROCKS, GROUP_DRY_LAND, GROUPS };

typedef struct proto_def {
    const char *name;
    void (*make)(builder *b, uint64_t *rng, double detail, const void *shape);
    const void *shape;
    double per_scale;     /* instances per unit of scale (r_k in scenes.h) */
    int group;            /* where its instances stand */
    double window[2];     /* GROUP_FOREST: the share of the forests it grows in */
} proto_def;

static const conifer_shape spruce = {16, 0.3, 0.12, 3.5, 0.35, 14, 5, 5, 8};
static const conifer_shape pine = {18, 0.35, 0.55, 3.0, 0.05, 8, 6, 6, 10};
static const broadleaf_shape oak = {11, 0.4, 0.4, 4.5, 0.6, 6, 2400, 0.3, 1.0};
static const broadleaf_shape birch = {14, 0.18, 0.45, 2.6, 1.6, 5, 1600, 0.2, 0.8};
static const broadleaf_shape shrub = {1, 0.04, 0.05, 1.0, 1.2, 5, 500, 0.1, 0.45};
static const broadleaf_shape tropical_bush = {1.2, 0.05, 0.05, 1.2, 1.0, 5, 400, 0.25, 0.5};
static const rock_shape boulder = {1.5, 300}, stone = {0.6, 120};
static const palm_shape palm = {9, 0.03, 3.5, 9, 60}, leaning_palm = {7, 0.18, 3.0, 8, 60};

/* Instances come in runs of one prototype, in this order.  Forests: the
** species' windows overlap, so there are pure and mixed stands. */
static const proto_def landscape_protos[] = {
    {"spruce", make_conifer, &spruce, 500, GROUP_FOREST, {0.0, 0.6}},
    {"pine", make_conifer, &pine, 350, GROUP_FOREST, {0.2, 0.7}},
    {"oak", make_broadleaf, &oak, 450, GROUP_FOREST, {0.4, 1.0}},
    {"birch", make_broadleaf, &birch, 400, GROUP_FOREST, {0.5, 1.0}},
    {"bush", make_broadleaf, &shrub, 800, GROUP_FOREST, {0.0, 1.0}},
    {"grass", make_tuft, NULL, 3000, GROUP_MEADOW, {0, 1}},
    {"boulder", make_rock, &boulder, 150, GROUP_ROCKS, {0, 1}},
    {"stone", make_rock, &stone, 100, GROUP_ROCKS, {0, 1}},
};

static const proto_def island_protos[] = {
    {"palm", make_palm, &palm, 1500, GROUP_DRY_LAND, {0, 1}},
    {"leaning palm", make_palm, &leaning_palm, 1000, GROUP_DRY_LAND, {0, 1}},
    {"bush", make_broadleaf, &tropical_bush, 2000, GROUP_DRY_LAND, {0, 1}},
    {"grass", make_tuft, NULL, 5000, GROUP_DRY_LAND, {0, 1}},
    {"rock", make_rock, &boulder, 400, GROUP_DRY_LAND, {0, 1}},
};

#define MAX_PROTOS 8

/* Groups on the landscape: members per group (so their number follows
** the instances) and the range of their radii in metres. */
typedef struct group_kind {
    uint64_t key;                 /* the group centres' random numbers */
    double members, radius_lo, radius_hi;
} group_kind;

static const group_kind group_kinds[GROUPS] = {
    {0x466F72657374ull, 60, 30, 80},     /* forests */
    {0x4D6561646F77ull, 200, 15, 45},    /* meadows */
    {0x526F636B73ull, 5, 3, 9},          /* groups of rocks */
    {0, 1, 0, 0},                        /* dry land: the island's, no groups */
};

/* ===================================================================== */
/* Instanced scenes: the scene                                           */
/* ===================================================================== */

#define WORLD_SHARE 0.55         /* of the budget 100000 * scale: world triangles */
#define INSTANCE_KEY 0x496E7374616E6365ull
#define PROTOTYPE_KEY 0x50726F746F747970ull

typedef struct instanced_kind instanced_kind;

struct ex_instanced_scene {
    const instanced_kind *kind;
    double scale, detail;
    uint64_t seed;
    uint32_t first[MAX_PROTOS + 1];        /* prototype k's instances: first[k] .. first[k+1]-1 */
    uint64_t proto_triangles[MAX_PROTOS];
    uint64_t proto_vertices[MAX_PROTOS];
    part_log proto_parts[MAX_PROTOS];
    uint64_t world_triangles, world_vertices;
    part_log world_parts;
    /* the landscape */
    double side;
    terrain ground;
    patch land;
    grid terrain;
    uint32_t groups[GROUPS];
    /* the island */
    island *islands;
    uint32_t island_count;
    double half_side;
    grid island;                           /* every island's grid */
};

struct instanced_kind {
    const char *name;
    const proto_def *protos;
    uint32_t proto_count;
    int (*setup)(ex_instanced_scene *s);                    /* 0: out of memory */
    void (*world)(builder *b, const ex_instanced_scene *s);
    void (*base)(const ex_instanced_scene *s, const proto_def *d, uint64_t *rng, double at[3]);
};

/* ---- heights on the world's own triangles ---- */

/* Vertex (ring, seg) of a gridded surface exactly as emit_surface makes it
** (the float, widened); ring -1 is the start pole. */
static void grid_vertex(const grid *g, surface_fn fn, const void *shape, int64_t row,
                        uint32_t seg, double out[3])
{
    double p[3], du = 1.0 / ((g->flags & WRAP_U) ? g->segs : g->segs - 1);
    float f[3];
    int k;
    if (row < 0) fn(shape, 0, 0, p);
    else fn(shape, (seg % g->segs) * du, grid_v(g, (uint32_t)row), p);
    put_vertex(f, &world, p);
    for (k = 0; k < 3; k++) out[k] = f[k];
}

/* The height of the plane of triangle (a, b, c) at (x, z) into *h when
** (x, z) lies deeper inside the triangle's shadow on the xz plane than
** *best (the smallest barycentric coordinate: < 0 outside). */
static void triangle_height(const double a[3], const double b[3], const double c[3],
                            double x, double z, double *best, double *h)
{
    double e1x = b[0] - a[0], e1z = b[2] - a[2], e2x = c[0] - a[0], e2z = c[2] - a[2];
    double px = x - a[0], pz = z - a[2], d = e1x * e2z - e2x * e1z, u, v, inside;
    if (d == 0) return;   /* seen edge-on: never the one under a point */
    u = (px * e2z - e2x * pz) / d;
    v = (e1x * pz - px * e1z) / d;
    inside = fmin(1 - u - v, fmin(u, v));
    if (inside <= *best) return;
    *best = inside;
    *h = a[1] + u * (b[1] - a[1]) + v * (c[1] - a[1]);
}

/* The triangles of the cell between rings lo and lo + 1 at segment seg (lo
** = -1: the start pole's fan), as put_band and put_fan make them. */
static void cell_height(const grid *g, surface_fn fn, const void *shape, int64_t lo,
                        uint32_t seg, double x, double z, double *best, double *h)
{
    uint32_t seg2 = (seg + 1) % g->segs;
    double lo1[3], lo2[3], hi1[3], hi2[3];
    grid_vertex(g, fn, shape, lo + 1, seg, hi1);
    grid_vertex(g, fn, shape, lo + 1, seg2, hi2);
    if (lo < 0) {
        grid_vertex(g, fn, shape, -1, 0, lo1);
        triangle_height(lo1, hi2, hi1, x, z, best, h);
        return;
    }
    grid_vertex(g, fn, shape, lo, seg, lo1);
    grid_vertex(g, fn, shape, lo, seg2, lo2);
    triangle_height(lo1, lo2, hi2, x, z, best, h);
    triangle_height(lo1, hi2, hi1, x, z, best, h);
}

static int64_t clamp_index(double i, int64_t lo, int64_t hi)
{
    return i < (double)lo ? lo : i > (double)hi ? hi : (int64_t)i;
}

/* The terrain grid's height at (x, z): ring runs along x, segment along z
** (patch_point). */
static double landscape_height(const ex_instanced_scene *s, double x, double z)
{
    const grid *g = &s->terrain;
    double best = -INFINITY, h = 0;
    int64_t row = clamp_index(floor((x - s->land.x0) / s->land.size * (g->rings - 1)), 0,
                              (int64_t)g->rings - 2);
    int64_t seg = clamp_index(floor((z - s->land.z0) / s->land.size * (g->segs - 1)), 0,
                              (int64_t)g->segs - 2);
    cell_height(g, patch_point, &s->land, row, (uint32_t)seg, x, z, &best, &h);
    return h;
}

/* An island's dome at (x, z).  Ring i of the dome lies at radius (i + 1) /
** D * rim (D dome rings; grid_v with two poles), segment j at angle 2 pi j
** / segs, and the edges between rings are radial; a ring's chords cut
** inside its circle, so a point between rings i and i + 1 lies in that
** band or, near the outer ring, in the next one: both are tried. */
static double island_surface_height(const ex_instanced_scene *s, const island *isl, double x,
                                    double z)
{
    const grid *g = &s->island;
    double dx = x - isl->cx, dz = z - isl->cz, a = atan2(dz, dx), best = -INFINITY, h = 0;
    uint32_t dome = g->rings - isl->under_rings, seg;
    int64_t row, lo;
    if (a < 0) a += 2 * PI;
    seg = (uint32_t)(a / (2 * PI) * g->segs) % g->segs;
    row = clamp_index(floor(sqrt(dx * dx + dz * dz) / (ISLAND_RIM * isl->radius) * dome) - 1, -1,
                       (int64_t)g->rings - 2);
    for (lo = row; lo <= row + 1 && lo <= (int64_t)g->rings - 2; lo++)
        cell_height(g, island_point, isl, lo, seg, x, z, &best, &h);
    return h;
}

/* ---- the landscape ---- */

static int landscape_setup(ex_instanced_scene *s)
{
    uint64_t rng = s->seed;
    s->side = LANDSCAPE_SIDE * sqrt(s->scale);
    landscape_terrain(&rng, s->side, &s->ground, &s->land);
    s->terrain = terrain_grid(WORLD_SHARE * TRIANGLES_PER_SCALE * s->scale);
    return 1;
}

static void landscape_world(builder *b, const ex_instanced_scene *s)
{
    emit_ground(b, &s->land, &s->terrain);
}

/* A random point of a random group of the prototype's kind (within its
** window of the groups), on the terrain. */
static void landscape_base(const ex_instanced_scene *s, const proto_def *d, uint64_t *rng,
                           double at[3])
{
    const group_kind *kind = &group_kinds[d->group];
    uint32_t n = s->groups[d->group];
    double lo = floor(d->window[0] * n), hi = fmax(lo + 1, floor(d->window[1] * n));
    uint64_t centre = s->seed ^ kind->key ^ brt_mix64((uint64_t)(lo + floor(rnd(rng, 0, hi - lo))));
    double cx = rnd(&centre, -0.45, 0.45) * s->side, cz = rnd(&centre, -0.45, 0.45) * s->side;
    double radius = rnd(&centre, kind->radius_lo, kind->radius_hi);
    double a = rnd(rng, 0, 2 * PI), r = radius * sqrt(rnd(rng, 0, 1));
    /* on the terrain: a group at the edge is cut off there */
    at[0] = clamp(cx + r * cos(a), -0.49 * s->side, 0.49 * s->side);
    at[2] = clamp(cz + r * sin(a), -0.49 * s->side, 0.49 * s->side);
    at[1] = landscape_height(s, at[0], at[2]);
}

/* ---- the island ---- */

static int island_setup(ex_instanced_scene *s)
{
    uint64_t rng = s->seed;
    uint32_t i;
    s->island_count = island_count(s->scale);
    s->half_side = island_half_side(s->island_count);
    s->islands = malloc(s->island_count * sizeof *s->islands);
    if (!s->islands) return 0;
    for (i = 0; i < s->island_count; i++) {
        place_island(&rng, s->islands, i, s->half_side);
        s->island = island_grid(&s->islands[i], WORLD_SHARE * TRIANGLES_PER_SCALE * s->scale
                                / s->island_count);
    }
    return 1;
}

static void island_world(builder *b, const ex_instanced_scene *s)
{
    uint32_t i;
    mark_material(b, EX_MAT_SEA);
    emit_sea(b, s->half_side + 150);
    mark_material(b, EX_MAT_SAND);
    for (i = 0; i < s->island_count; i++)
        emit_surface(b, &s->island, island_point, &s->islands[i], &world);
}

/* A random spot on dry land of a random island, on its triangles.  After a
** few misses the island's centre: it is always dry (the peak is at least
** 15 m, the coast's noise at most 0.35 * 1.875 of it). */
static void island_base(const ex_instanced_scene *s, const proto_def *d, uint64_t *rng,
                        double at[3])
{
    uint32_t j = (uint32_t)rnd(rng, 0, s->island_count);
    const island *isl = &s->islands[j < s->island_count ? j : s->island_count - 1];
    (void)d;
    if (!dry_spot(rng, isl, at)) {
        at[0] = isl->cx;
        at[2] = isl->cz;
    }
    at[1] = island_surface_height(s, isl, at[0], at[2]);
}

static const instanced_kind instanced_kinds[] = {
    {"landscape", landscape_protos, sizeof landscape_protos / sizeof *landscape_protos,
     landscape_setup, landscape_world, landscape_base},
    {"island", island_protos, sizeof island_protos / sizeof *island_protos,
     island_setup, island_world, island_base},
};

/* ---- making parts: the world or one prototype, to a builder ---- */

typedef void (*part_fn)(builder *b, const ex_instanced_scene *s, uint32_t id);

static void world_part(builder *b, const ex_instanced_scene *s, uint32_t id)
{
    (void)id;
    s->kind->world(b, s);
}

static void prototype_part(builder *b, const ex_instanced_scene *s, uint32_t id)
{
    const proto_def *d = &s->kind->protos[id];
    uint64_t rng = s->seed ^ PROTOTYPE_KEY ^ brt_mix64(id);
    d->make(b, &rng, s->detail, d->shape);
}

/* Runs one part into b's output (b made by builder_init, its sink or emit
** set; parts logged when b->parts is not NULL). */
static brt_result run_part(const ex_instanced_scene *s, builder *b, part_fn fn, uint32_t id)
{
    if (builder_start(b, s->kind->name, s->scale)) fn(b, s, id);
    return builder_finish(b);
}

/* Counts a part: its triangles, vertices and material parts. */
static brt_result count_part(const ex_instanced_scene *s, part_fn fn, uint32_t id,
                             part_log *parts, uint64_t *triangles, uint64_t *vertices,
                             brt_error *err)
{
    builder b;
    brt_result r;
    builder_init(&b, OUT_COUNT, err);
    b.parts = parts;
    r = run_part(s, &b, fn, id);
    *triangles = b.triangles;
    *vertices = b.vertices;
    return r;
}

/* Streams a part's triangles to emit. */
static brt_result stream_part(const ex_instanced_scene *s, part_fn fn, uint32_t id,
                              brt_triangle_fn emit, void *emit_user, brt_error *err)
{
    builder b;
    builder_init(&b, OUT_TRIANGLES, err);
    b.emit = emit;
    b.emit_user = emit_user;
    return run_part(s, &b, fn, id);
}

/* The number of groups of each kind: their members' instances / members. */
static void count_groups(ex_instanced_scene *s)
{
    double members[GROUPS] = {0, 0, 0, 0};
    uint32_t k;
    int g;
    for (k = 0; k < s->kind->proto_count; k++)
        members[s->kind->protos[k].group] += s->first[k + 1] - s->first[k];
    for (g = 0; g < GROUPS; g++) {
        double n = floor(members[g] / group_kinds[g].members);
        s->groups[g] = n < 1 ? 1 : (uint32_t)n;
    }
}

/* Instances, groups and the parts' triangle counts and materials. */
static brt_result instanced_place(ex_instanced_scene *s, brt_error *err)
{
    brt_result r;
    uint32_t k;
    s->first[0] = 0;
    for (k = 0; k < s->kind->proto_count; k++)
        s->first[k + 1] = s->first[k] + (uint32_t)(s->kind->protos[k].per_scale * s->scale + 0.5);
    count_groups(s);
    if (!s->kind->setup(s)) {
        out_of_memory(err, s->kind->name, s->scale);
        return BRT_ENOMEM;
    }
    r = count_part(s, world_part, 0, &s->world_parts, &s->world_triangles, &s->world_vertices,
                   err);
    for (k = 0; k < s->kind->proto_count && r == BRT_OK; k++)
        r = count_part(s, prototype_part, k, &s->proto_parts[k], &s->proto_triangles[k],
                       &s->proto_vertices[k], err);
    return r;
}

brt_result ex_instanced_open(const char *name, double scale, uint64_t seed,
                             ex_instanced_scene **out, brt_error *err)
{
    ex_instanced_scene *s;
    brt_result r;
    size_t k;
    *out = NULL;
    for (k = 0; k < sizeof instanced_kinds / sizeof *instanced_kinds; k++)
        if (name && strcmp(name, instanced_kinds[k].name) == 0) break;
    if (k == sizeof instanced_kinds / sizeof *instanced_kinds)
        return brt_fail(err, BRT_EARG, "unknown instanced scene '%s' (built-in: landscape, island)",
                        name ? name : "(null)");
    if (!(scale > 0 && scale <= EX_SCENE_MAX_SCALE))
        return brt_fail(err, BRT_EARG, "%s: scale %g outside (0, %g]", name, scale,
                        EX_SCENE_MAX_SCALE);
    s = calloc(1, sizeof *s);
    if (!s) {
        out_of_memory(err, name, scale);
        return BRT_ENOMEM;
    }
    s->kind = &instanced_kinds[k];
    s->scale = scale;
    s->detail = scale < 1 ? 1 : pow(scale, 0.25);
    s->seed = seed;
    r = instanced_place(s, err);
    if (r != BRT_OK) {
        ex_instanced_close(s);
        return r;
    }
    *out = s;
    return BRT_OK;
}

void ex_instanced_close(ex_instanced_scene *s)
{
    if (!s) return;
    free(s->islands);
    free(s);
}

/* ---- instances ---- */

int ex_instanced_instance_prototype(const ex_instanced_scene *s, uint32_t inst)
{
    uint32_t k;
    for (k = 0; k < s->kind->proto_count; k++)
        if (inst < s->first[k + 1]) return (int)k;
    return -1;
}

/* Counter-based: instance inst's random numbers come from (seed, inst)
** alone, so any instance is made without the others. */
void ex_instanced_instance(const ex_instanced_scene *s, uint32_t inst, brt_instance *out)
{
    int proto = ex_instanced_instance_prototype(s, inst);
    uint64_t rng = s->seed ^ INSTANCE_KEY ^ brt_mix64(inst);
    double at[3], axis[3] = {0, 1, 0}, turn, size;
    xform x;
    int r, c;
    if (proto < 0) proto = 0;   /* never: callers stay below the count */
    s->kind->base(s, &s->kind->protos[proto], &rng, at);
    turn = rnd(&rng, 0, 2 * PI);
    size = rnd(&rng, EX_INSTANCE_SCALE_MIN, EX_INSTANCE_SCALE_MAX);
    if (rnd(&rng, 0, 1) < EX_INSTANCE_TILTED_SHARE) random_up(&rng, EX_INSTANCE_MAX_TILT, axis);
    x = xform_along(axis, turn, size, at);
    out->prototype = (uint32_t)proto;
    for (r = 0; r < 3; r++) {
        for (c = 0; c < 3; c++) out->xform[4 * r + c] = (float)x.m[r][c];
        out->xform[4 * r + 3] = (float)x.t[r];
    }
}

/* ---- the streams ---- */

static brt_result source_world(const void *user, brt_triangle_fn emit, void *emit_user,
                               brt_error *err)
{
    return stream_part(user, world_part, 0, emit, emit_user, err);
}

static brt_result source_prototype(const void *user, uint32_t id, brt_triangle_fn emit,
                                   void *emit_user, brt_error *err)
{
    const ex_instanced_scene *s = user;
    if (id >= s->kind->proto_count)
        return brt_fail(err, BRT_EARG, "%s: no prototype %lu (%lu prototypes)", s->kind->name,
                        (unsigned long)id, (unsigned long)s->kind->proto_count);
    return stream_part(s, prototype_part, id, emit, emit_user, err);
}

static brt_result source_instances(const void *user, brt_instance_fn emit, void *emit_user,
                                   brt_error *err)
{
    const ex_instanced_scene *s = user;
    uint32_t total = ex_instanced_instance_count(s), first, i, n;
    brt_instance *chunk = malloc(EX_INSTANCE_CHUNK * sizeof *chunk);
    brt_result r = BRT_OK;
    if (!chunk) {
        out_of_memory(err, s->kind->name, s->scale);
        return BRT_ENOMEM;
    }
    for (first = 0; first < total && r == BRT_OK; first += n) {
        n = total - first < EX_INSTANCE_CHUNK ? total - first : EX_INSTANCE_CHUNK;
        for (i = 0; i < n; i++) ex_instanced_instance(s, first + i, &chunk[i]);
        r = emit(emit_user, chunk, n, first, err);
    }
    free(chunk);
    return r;
}

void ex_instanced_source(const ex_instanced_scene *s, brt_scene_source *source)
{
    source->world.run = source_world;
    source->world.user = s;
    source->prototype_count = s->kind->proto_count;
    source->prototype = source_prototype;
    source->instances = source_instances;
    source->user = s;
}

/* ---- counts ---- */

uint32_t ex_instanced_instance_count(const ex_instanced_scene *s)
{
    return s->first[s->kind->proto_count];
}

uint64_t ex_instanced_world_triangles(const ex_instanced_scene *s)
{
    return s->world_triangles;
}

uint32_t ex_instanced_prototype_count(const ex_instanced_scene *s)
{
    return s->kind->proto_count;
}

uint64_t ex_instanced_prototype_triangles(const ex_instanced_scene *s, uint32_t id)
{
    return id < s->kind->proto_count ? s->proto_triangles[id] : 0;
}

const char *ex_instanced_prototype_name(const ex_instanced_scene *s, uint32_t id)
{
    return id < s->kind->proto_count ? s->kind->protos[id].name : NULL;
}

uint64_t ex_instanced_unique(const ex_instanced_scene *s)
{
    uint64_t sum = s->world_triangles;
    uint32_t k;
    for (k = 0; k < s->kind->proto_count; k++) sum += s->proto_triangles[k];
    return sum;
}

uint64_t ex_instanced_instanced(const ex_instanced_scene *s)
{
    uint64_t sum = s->world_triangles;
    uint32_t k;
    for (k = 0; k < s->kind->proto_count; k++)
        sum += (uint64_t)(s->first[k + 1] - s->first[k]) * s->proto_triangles[k];
    return sum;
}

void ex_instanced_counts(const char *name, double scale, uint64_t *unique, uint64_t *instanced,
                         uint32_t *instances)
{
    ex_instanced_scene *s;
    brt_error err;
    *unique = *instanced = 0;
    *instances = 0;
    if (ex_instanced_open(name, scale, 1, &s, &err) != BRT_OK) return;
    *unique = ex_instanced_unique(s);
    *instanced = ex_instanced_instanced(s);
    *instances = ex_instanced_instance_count(s);
    ex_instanced_close(s);
}

/* ---- baked: ex_scene_write, _count and _stream of the landscape and island ---- */

/* Point p of object space through an instance's row-major 3x4 matrix m:
** each coordinate summed in double and rounded to float once. */
static void bake_point(const float m[12], const float p[3], float out[3])
{
    int r;
    for (r = 0; r < 3; r++)
        out[r] = (float)((double)m[4 * r] * p[0] + (double)m[4 * r + 1] * p[1]
                         + (double)m[4 * r + 2] * p[2] + (double)m[4 * r + 3]);
}

/* Prototype id as an indexed mesh, in object space. */
static brt_result bake_prototype(const ex_instanced_scene *s, uint32_t id, brt_mesh *mesh,
                                 brt_error *err)
{
    builder b;
    collector c;
    brt_result r;
    memset(&c, 0, sizeof c);
    c.name = s->kind->name;
    c.scale = s->scale;
    builder_init(&b, OUT_INDEXED, err);
    r = collector_open(&c, s->proto_vertices[id], s->proto_triangles[id], &b.sink, err);
    if (r == BRT_OK) r = run_part(s, &b, prototype_part, id);
    return collector_close(&c, r, mesh);
}

/* Instance inst of prototype mesh m to b's output: its vertices placed
** into xyz, then index triples shifted past the vertices so far (into
** tri), or corner triples (into tri). */
static brt_result bake_instance(builder *b, const ex_instanced_scene *s, uint32_t inst,
                                const brt_mesh *m, float *xyz, void *tri)
{
    brt_instance in;
    brt_result r;
    size_t i;
    ex_instanced_instance(s, inst, &in);
    for (i = 0; i < 3 * (size_t)m->vertex_count; i += 3)
        bake_point(in.xform, m->positions + i, xyz + i);
    if (b->out == OUT_INDEXED) {
        for (i = 0; i < 3 * (size_t)m->triangle_count; i++)
            ((uint32_t *)tri)[i] = m->indices[i] + (uint32_t)b->vertices;
        r = b->sink.vertices(b->sink.user, xyz, m->vertex_count, b->err);
        if (r == BRT_OK) r = b->sink.triangles(b->sink.user, tri, m->triangle_count, b->err);
    } else {
        for (i = 0; i < 3 * (size_t)m->triangle_count; i++)
            memcpy((float *)tri + 3 * i, xyz + 3 * (size_t)m->indices[i], 12);
        r = b->emit(b->emit_user, tri, m->triangle_count, (uint32_t)b->triangles, b->err);
    }
    b->vertices += m->vertex_count;
    b->triangles += m->triangle_count;
    return r;
}

/* Every instance of prototype id, in the instance stream's order. */
static brt_result bake_instances(builder *b, const ex_instanced_scene *s, uint32_t id)
{
    brt_mesh m;
    brt_result r = bake_prototype(s, id, &m, b->err);
    float *xyz = r == BRT_OK ? malloc(12 * (size_t)m.vertex_count) : NULL;
    void *tri = xyz ? malloc(36 * (size_t)m.triangle_count) : NULL;
    uint32_t inst;
    if (r == BRT_OK && !tri) {
        out_of_memory(b->err, s->kind->name, s->scale);
        r = BRT_ENOMEM;
    }
    for (inst = s->first[id]; inst < s->first[id + 1] && r == BRT_OK; inst++)
        r = bake_instance(b, s, inst, &m, xyz, tri);
    free(xyz);
    free(tri);
    brt_mesh_free(&m);
    return r;
}

/* The baked scene's size into b (vertices, triangles); BRT_EARG when the
** numbers pass 32 bits, as a builder's: the landscape above scale 100 or
** so (mkscene's .pbrt writes it at any scale). */
static brt_result bake_count(builder *b, const ex_instanced_scene *s)
{
    uint32_t k;
    b->vertices = s->world_vertices;
    b->triangles = ex_instanced_instanced(s);
    for (k = 0; k < s->kind->proto_count; k++)
        b->vertices += (uint64_t)(s->first[k + 1] - s->first[k]) * s->proto_vertices[k];
    if (b->vertices <= UINT32_MAX && b->triangles <= UINT32_MAX) return BRT_OK;
    return brt_fail(b->err, BRT_EARG, "%s: scale %g baked needs more than 2^32 - 1 vertices or "
                    "triangles (a .pbrt file keeps the instances)", s->kind->name, s->scale);
}

/* The instanced scene of the recipe as one mesh: the world part as it
** streams, then each instance's prototype in world space (bake_point), in
** the instance stream's order.  Holds one prototype and its placed copy. */
static brt_result bake(builder *b, const ex_scene_recipe *recipe)
{
    ex_instanced_scene *s;
    brt_result r = ex_instanced_open(recipe->name, recipe->scale, recipe->seed, &s, b->err);
    uint32_t k;
    if (r != BRT_OK) return r;
    r = bake_count(b, s);
    if (r == BRT_OK && b->out != OUT_COUNT) {
        b->vertices = b->triangles = 0;
        r = run_part(s, b, world_part, 0);
        for (k = 0; k < s->kind->proto_count && r == BRT_OK; k++) r = bake_instances(b, s, k);
    }
    ex_instanced_close(s);
    return r;
}

/* ---- colours ---- */

static ex_material part_material(const part_log *log, uint64_t total, uint32_t prim)
{
    uint32_t k = log->count;
    if (prim >= total) return EX_MAT_NONE;
    while (k > 0 && log->start[k - 1] > prim) k--;
    return k > 0 ? (ex_material)log->material[k - 1] : EX_MAT_NONE;
}

ex_material ex_instanced_material(const ex_instanced_scene *s, uint32_t inst, uint32_t prim)
{
    int proto;
    if (inst == BRT_NO_INST) return part_material(&s->world_parts, s->world_triangles, prim);
    proto = ex_instanced_instance_prototype(s, inst);
    if (proto < 0) return EX_MAT_NONE;
    return part_material(&s->proto_parts[proto], s->proto_triangles[proto], prim);
}

void ex_material_colour(ex_material m, float rgb[3])
{
    static const float table[EX_MAT_COUNT][3] = {
        {0.30f, 0.42f, 0.18f},   /* terrain: grassland */
        {0.45f, 0.43f, 0.40f},   /* rock */
        {0.80f, 0.72f, 0.52f},   /* sand */
        {0.05f, 0.20f, 0.35f},   /* sea */
        {0.30f, 0.20f, 0.12f},   /* bark */
        {0.20f, 0.45f, 0.10f},   /* leaves */
        {0.08f, 0.25f, 0.12f},   /* conifer needles */
        {0.25f, 0.50f, 0.15f},   /* palm fronds */
        {0.45f, 0.60f, 0.20f},   /* grass */
        {1.00f, 0.00f, 1.00f},   /* none */
    };
    if ((int)m < 0 || m >= EX_MAT_COUNT) m = EX_MAT_NONE;
    memcpy(rgb, table[m], sizeof table[m]);
}

void ex_instanced_colour(const ex_instanced_scene *s, uint32_t inst, uint32_t prim, float rgb[3])
{
    ex_material_colour(ex_instanced_material(s, inst, prim), rgb);
}
