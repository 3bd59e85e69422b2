/*
** bvh.c -- the watertight ray/triangle test and the triangle BVH.
**
** RAY/TRIANGLE TEST: Woop, Benthin and Wald, "Watertight Ray/Triangle
** Intersection", JCGT 2(1), 2013.  Per ray: kz is the axis of the largest
** |dir| component, kx/ky the next two (swapped when dir[kz] < 0 so the
** winding is kept), and the shear constants Sx, Sy, Sz map the ray onto the
** +z axis.  Per triangle: vertices relative to the origin are sheared, the
** 2D edge functions U, V, W are evaluated (again in double precision when
** one of them is exactly 0, as in the paper, so an edge through the ray is
** decided the same way for both triangles sharing it), and a hit needs all
** three of one sign (no back-face culling).  U, V, W weigh v0, v1, v2, so
** Embree's barycentrics are u = V/det, v = W/det.  A hit counts when
** tnear <= t <= tfar, tested on the final float t.
**
** ONE CORE, TWO CALLERS.  brt_intersect_triangle and the BVH leaves call
** the same static inline tri_intersect() with the same per-ray constants
** (struct tri_ray), and stored triangles are the input vertices unchanged,
** so the BVH returns bit-identical t, u, v: a brute-force loop over
** brt_intersect_triangle is an exact oracle for it.
**
** NODE LAYOUT (4-wide BVH, one flat array, indices only; 64 bytes a node,
** one cache line; the blob's layout, walked in place by batching points):
**   struct qnode { float org[3], scale[3]; uint32_t q[6];
**                  uint32_t first_node, first_tri, vertex_base;
**                  uint8_t count[4]; }
**   Slot i's box is quantized in the node's frame: plane q of axis a is
**   org[a] + q * scale[a] (decode_plane), with q the 8-bit lane i of row
**   q[0..2] (min x, y, z) or q[3..5] (max x, y, z).  Slot i is
**     count[i] == 0: an inner node: inner slots come first and take
**                    first_node, first_node + 1, ... (always > the
**                    parent's index, siblings consecutive in memory);
**     count[i] 1..MAX_LEAF: a leaf; the leaf slots take consecutive
**                    triangle ranges from first_tri on, in slot order;
**     count[i] == EMPTY_COUNT: empty, masked out before the box test.
**   Node 0 is the root (no nodes at all for 0 triangles).  Then the
**   vertices (3 floats each, exactly as given; equal bits stored once as
**   far as a node can reach them), the reported triangle numbers prim[]
**   (read only on a hit), and per triangle 3 uint16 corner offsets from
**   its node's vertex_base.  Bytes: 64 per node, 12 per vertex, 10 per
**   triangle; build/bench_bvh MESH prints the total per triangle.
**
** WHY THE QUANTIZED BOXES KEEP PRUNING EXACT.  The build quantizes each
** padded child box outward (min planes down, max planes up, checked by
** decoding: quantize_down/up), so the decoded box contains the padded
** box of every triangle below it (brt_bvh_check verifies exactly that).
** The traversal decodes with the same decode_plane and runs the one
** monotone box test (box_span4) on the decoded floats.  A triangle's hit
** distance is clamped into its own padded box's interval (hit_distance),
** and a box containing that box is entered no later and left no later
** bit for bit (rule 2 of the README's Floating point section), so every
** decoded box around a hit at t is entered at or before t: pruning a
** slot whose entry exceeds the closest t so far never loses a hit, and
** the hits are those of the float boxes, byte for byte.
**
** RESIDENT LAYOUT (a BVH built in memory -- the direct mode's and its
** instance prototypes' -- and a blob the geometry cache decodes,
** brt_bvh_decode).  The same tree decoded once: node i
** (struct fnode, 128 bytes) holds decode_boxes of qnode i -- the floats
** the quantized walk decodes at every visit, by the same decode_row, so
** each box contains exactly what the quantized box contains and pruning
** is exact for the same reason -- with each slot's child node or first
** block stored; a leaf's triangles are copied in slot order into blocks
** of four (struct tri4: corners as structures of arrays, the stored
** vertices' bits, and the reported numbers).  The walk tests the four
** slots' boxes with the one box_span4, and a block's four triangles with
** a vectorized filter of tri_intersect's own edge functions; the lanes it
** keeps run tri_intersect itself, so hits are bit for bit those of the
** quantized walk (brt_bvh_check compares the resident layout, byte for
** byte, with what the quantized nodes decode to).  WHY TWO LAYOUTS: the
** blob stays quantized for its bytes on disk and in a cache that cannot
** hold every point decoded (the resident layout takes several times the
** bytes: far fewer points would fit, and the method is there to spare
** loads), while decoding at every visit costs the walk several
** times the box test itself, which the resident walk does not pay.  So a
** blob opened in place (brt_bvh_blob_open) keeps the quantized walk, and
** the geometry cache decodes it only into room that every blob leaves
** (batchrt.c, layer 8).  make bench-embree times the direct mode (always
** resident) and the batched one with and without decoding, and prints
** the blob bytes per triangle.
**
** BUILD: binned SAH (Wald 2007, "On fast construction of SAH-based
** bounding volume hierarchies") into a binary tree, then collapsed into the
** 4-wide tree by repeatedly opening the child of largest surface area (as
** Embree does).  16 bins per axis (fewer, one per triangle, in nodes of
** under 16): Wald reports 16 bins within a few percent of the full-sweep
** SAH, and more bins cost build time.  Costs C_TRAV = 10, C_ISECT = 1,
** and leaves of at most MAX_LEAF = 16 triangles: a node visit (its box
** test, the ordering, the stack, and for the rays that wait on memory a
** miss) costs many triangle tests, since the walks test a leaf four
** triangles at once (tri4_candidates), and the larger leaves this makes
** spare nodes, bytes (their triangles share more vertices) and visits.
** make bench-embree times the walk on camera, random and bounce rays, the
** measure for any other choice.  Below depth SAH_DEPTH the split is the
** SAH one; deeper (pathological inputs only) the range is halved, so the binary
** depth is at most SAH_DEPTH + 32 = MAX_DEPTH and the 4-wide depth no
** more: the traversal stack of 3*MAX_DEPTH+1 entries never overflows.
** Degenerate triangles are binned like any other and stay in the tree.
**
** FLOATING-POINT REASONING OF THE BOX TEST.  The triangle test rounds, so
** it may report a hit for a ray that in exact arithmetic passes a tiny bit
** outside the triangle, and its t is rounded too.  The error of its
** translated and sheared coordinates is a few ulps of the coordinates of
** the vertices and of the origin (|v - o| <= |v| + |o| per component).
** So the box test is made conservative by padding in space, not in t:
**   - every stored box is grown by PAD_REL * (largest |coordinate| of the
**     box), rounding outward (the pad is many ulps, so it survives rounding);
**   - per ray, the origin used for near planes is moved forward and the one
**     for far planes backward by PAD_REL * (largest |origin component|).
** A slab distance (b - o) * (1/d) has relative error below gamma(3) (Ize
** 2013, "Robust BVH ray traversal"), i.e. a spatial error below
** gamma(3)*(|b|+|o|) along the axis, which the same pads cover; this is why
** no extra 1+2*gamma(3) factor on tmax is needed.  PAD_REL = 16*FLT_EPSILON
** (32 half-ulps) leaves a margin of about 4 over the sum of these bounds.
** (Needle triangles whose shortest edge is below an ulp of their size can
** have larger edge-function errors; the brute-force tests hunt for them.)
** Pruning is inclusive: a box entered at exactly the current hit's t is
** visited, since an equal t with a lower prim wins.  With dir[a] == +-0,
** 1/dir is +-inf and (b - o) * inf may be NaN (origin on the plane): the
** max/min below are written "x > lo ? x : lo" so a NaN never narrows the
** interval -- a ray lying in a slab's plane is inside the closed slab.
**
** Rays with a NaN anywhere, an inf in the origin or direction, an all-zero
** direction, or tnear > tfar never hit (checked once per ray).
*/
#include "internal.h"
/* The oracles and checkers the library holds for its tests; the hooks
** only when compiled with BRT_TESTING (testing.h). */
#include "testing.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* GCC's -O2 would call box_span4 rather than inline it into traverse(),
** a call at every node of the BVH walk (make bench measures the walk's
** speed); other compilers decide. */
#if defined(__GNUC__)
#define ALWAYS_INLINE __attribute__((always_inline))
#else
#define ALWAYS_INLINE
#endif

#define BINS 16
#define MAX_LEAF 16
#define C_TRAV 10.0f
#define C_ISECT 1.0f
#define SAH_DEPTH 64
#define MAX_DEPTH (SAH_DEPTH + 32)
#define STACK_SIZE (3 * MAX_DEPTH + 1)
#define PAD_REL (16.0f * FLT_EPSILON)
#define EMPTY_COUNT 0xFFu   /* count[] of an empty slot */
#define VERTEX_WINDOW 65536u /* 16-bit corner offsets from a node's vertex_base */
#define NODE_NEW_VERTICES (4u * 3u * MAX_LEAF)   /* corners a node may add */
#define BLOB_MAGIC 0x32485642u   /* "BVH2" little endian */
#define BLOB_HEADER 64u        /* bytes: a cache line, so nodes stay aligned */

typedef struct qnode {
    float org[3];         /* the frame: plane q of axis a is */
    float scale[3];       /*   org[a] + q * scale[a] (decode_plane) */
    uint32_t q[6];        /* min x,y,z rows then max x,y,z rows: slot i's
                          ** 8-bit plane in bits 8i..8i+7 (decode_row) */
    uint32_t first_node;  /* the inner slots' children, consecutive */
    uint32_t first_tri;   /* the leaf slots' triangles, consecutive */
    uint32_t vertex_base; /* the leaves' corners are vertex_base + idx */
    uint8_t count[4];     /* 0 inner, 1..MAX_LEAF leaf, EMPTY_COUNT empty */
} qnode;

typedef char qnode_is_one_cache_line[sizeof(qnode) == 64 ? 1 : -1];

/* The resident layout (see RESIDENT LAYOUT above): node i is qnode i
** decoded, its leaves' triangles copied into blocks of four. */
typedef struct fnode {
    float box[6][4];      /* decode_boxes of qnode i, bit for bit (all slots) */
    uint32_t child[4];    /* inner slot: node index; leaf slot: first block */
    uint8_t count[4];     /* qnode i's count[] */
    uint32_t valid;       /* slot_valid of qnode i */
    uint32_t zero[2];     /* 0: the node fills two cache lines */
} fnode;

typedef struct tri4 {
    float v[3][3][4];     /* corner, axis, lane: the vertices' bits as stored */
    uint32_t prim[4];     /* reported numbers; lanes past the leaf's end 0 */
} tri4;

typedef char fnode_is_two_cache_lines[sizeof(fnode) == 128 ? 1 : -1];
/* prefetch_resident's lines: a block of 160 bytes starts at a multiple of
** 32 (after 128-byte nodes, in a 64-byte aligned allocation). */
typedef char tri4_is_160_bytes[sizeof(tri4) == 160 ? 1 : -1];

struct brt_bvh {
    const qnode *nodes;   /* node_count, root first */
    const float *verts;   /* 3 floats per vertex, exactly as given */
    const uint32_t *prim; /* reported number of each stored triangle */
    const uint16_t *idx;  /* 3 corner offsets per triangle, in leaf order */
    uint32_t node_count, vert_count, tri_count;
    void *owned;          /* one allocation holding all four, or NULL */
    fnode *fnodes;        /* the resident layout (node_count), or NULL */
    tri4 *blocks;         /* block_count, in leaf order */
    uint32_t block_count;
};

/* ===================================================================== */
/* Conservative ray/box test of four slots at once                       */
/* ===================================================================== */

static float max_abs3(const float p[3])
{
    float m = fabsf(p[0]);
    if (fabsf(p[1]) > m) m = fabsf(p[1]);
    if (fabsf(p[2]) > m) m = fabsf(p[2]);
    return m;
}

void brt_ray_prepare(const brt_ray *ray, brt_ray_prep *prep)
{
    const float pad = PAD_REL * max_abs3(ray->org);
    int a;
    for (a = 0; a < 3; a++) {
        const int neg = signbit(ray->dir[a]) != 0;
        prep->inv[a] = 1.0f / ray->dir[a];
        prep->negative[a] = neg;
        prep->org_near[a] = neg ? ray->org[a] - pad : ray->org[a] + pad;
        prep->org_far[a] = neg ? ray->org[a] + pad : ray->org[a] - pad;
    }
    prep->tnear = ray->tnear;
    prep->tfar = ray->tfar;
    prep->valid = brt_ray_valid(ray);
}

/* The four-lane copy of an already prepared ray (brt_box_lanes), once per
** walk: broadcasting the nine scalars at every node would cost each visit
** (callgrind on build/trace --batched counts it). */
static inline ALWAYS_INLINE void box_lanes_of(const brt_ray_prep *prep, brt_box_lanes *b)
{
    int a, i;
    for (a = 0; a < 3; a++) {
        for (i = 0; i < 4; i++) {
            b->org_near[a][i] = prep->org_near[a];
            b->org_far[a][i] = prep->org_far[a];
            b->inv[a][i] = prep->inv[a];
        }
        b->near_row[a] = prep->negative[a] ? a + 3 : a;
        b->far_row[a] = prep->negative[a] ? a : a + 3;
        b->near_off[a] = (size_t)b->near_row[a] * sizeof(float[4]);
        b->far_off[a] = (size_t)b->far_row[a] * sizeof(float[4]);
    }
}

void brt_box_lanes_of(const brt_ray_prep *prep, brt_box_lanes *lanes)
{
    box_lanes_of(prep, lanes);
}

/* The slab test of one box that is already padded: entry and exit of the
** segment [tl, th] (NaN from a zero direction on a slab plane never
** narrows it).  box_test4 below is the same arithmetic on four boxes. */
static inline int slab_span(const brt_ray_prep *r, const float lo[3], const float hi[3],
                            float tl, float th, float *entry, float *exit)
{
    int a;
    for (a = 0; a < 3; a++) {
        const float t0 = ((r->negative[a] ? hi[a] : lo[a]) - r->org_near[a]) * r->inv[a];
        const float t1 = ((r->negative[a] ? lo[a] : hi[a]) - r->org_far[a]) * r->inv[a];
        tl = t0 > tl ? t0 : tl;
        th = t1 < th ? t1 : th;
    }
    *entry = tl;
    *exit = th;
    return tl <= th;
}

/* Grows a box by PAD_REL of its largest |coordinate| (see the header). */
void brt_box_pad(const float lo[3], const float hi[3], float plo[3], float phi[3])
{
    float m = 0.0f, pad;
    int a;
    for (a = 0; a < 3; a++) {
        if (fabsf(lo[a]) > m) m = fabsf(lo[a]);
        if (fabsf(hi[a]) > m) m = fabsf(hi[a]);
    }
    pad = PAD_REL * m;
    for (a = 0; a < 3; a++) {
        /* Clamped to +-FLT_MAX (monotone, like the rest), so a quantized
        ** node's frame (set_frame) never starts at an infinity. */
        plo[a] = lo[a] - pad > -FLT_MAX ? lo[a] - pad : -FLT_MAX;
        phi[a] = hi[a] + pad < FLT_MAX ? hi[a] + pad : FLT_MAX;
    }
}

int brt_box_span(const brt_ray_prep *prep, const float lo[3], const float hi[3],
                 float tmin, float tmax, float *entry, float *exit)
{
    return slab_span(prep, lo, hi, tmin, tmax, entry, exit);
}

/* ===================================================================== */
/* Per-ray constants and the shared ray/triangle core                    */
/* ===================================================================== */

typedef struct tri_ray {
    float org[3], dir[3];
    int kx, ky, kz;
    float sx, sy, sz;
} tri_ray;

/* Section 3 of Woop et al.: the axis permutation and shear constants. */
static void tri_ray_setup(const brt_ray *ray, tri_ray *r)
{
    const float *d = ray->dir;
    int kz = 0, swap;
    if (fabsf(d[1]) > fabsf(d[kz])) kz = 1;
    if (fabsf(d[2]) > fabsf(d[kz])) kz = 2;
    r->kz = kz;
    r->kx = (kz + 1) % 3;
    r->ky = (kz + 2) % 3;
    if (d[kz] < 0.0f) { swap = r->kx; r->kx = r->ky; r->ky = swap; }
    r->sx = d[r->kx] / d[kz];
    r->sy = d[r->ky] / d[kz];
    r->sz = 1.0f / d[kz];
    memcpy(r->org, ray->org, sizeof r->org);
    memcpy(r->dir, ray->dir, sizeof r->dir);
}

/* Woop's values for one triangle: the sheared corners (x, y; z times
** sz) and the edge functions. */
typedef struct woop_values {
    float ax, ay, bx, by, cx, cy, zs0, zs1, zs2, eu, ev, ew;
} woop_values;

static inline int edges_certain(const woop_values *wv);   /* below, with the error bounds */

/* The span of t in which the ray's point lies in the triangle's prism --
** the three planes through its edges along its normal n, each moved out
** by grow -- in double: [*lo, *hi], 0 when empty.  w = p0 - o, e1 = p1 -
** p0, e2 = p2 - p0.  n x edge points into the triangle (n = e1 x e2). */
static int prism_span(const double w[3], const double e1[3], const double e2[3], const double n[3],
                      const float dir[3], double grow, double *lo, double *hi)
{
    double edge[3][3], from[3][3];
    int i, a;
    *lo = -INFINITY;
    *hi = INFINITY;
    for (a = 0; a < 3; a++) {
        edge[0][a] = e1[a];
        edge[1][a] = e2[a] - e1[a];
        edge[2][a] = -e2[a];
        from[0][a] = w[a];              /* each edge's first corner, less o */
        from[1][a] = w[a] + e1[a];
        from[2][a] = w[a] + e2[a];
    }
    for (i = 0; i < 3; i++) {
        const double m[3] = {n[1] * edge[i][2] - n[2] * edge[i][1], n[2] * edge[i][0] - n[0] * edge[i][2],
                             n[0] * edge[i][1] - n[1] * edge[i][0]};
        /* inside: m . (o + t d - corner) >= -grow |m|, i.e. c + t b >= 0 */
        const double c = -(m[0] * from[i][0] + m[1] * from[i][1] + m[2] * from[i][2]) +
                         grow * sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2]);
        const double b = m[0] * dir[0] + m[1] * dir[1] + m[2] * dir[2];
        if (b > 0.0 && -c / b > *lo) *lo = -c / b;
        else if (b < 0.0 && c / -b < *hi) *hi = c / -b;
        else if (b == 0.0 && c < 0.0) return 0;
    }
    return *lo <= *hi;
}

/* The hit distance, once the ray is known to pass through the triangle:
** from the plane equation in double, since Woop's T/det loses accuracy for
** rays that graze the triangle (its weights are then tiny differences),
** then clamped into the interval in which the ray is inside the
** triangle's padded bounding box under the one box test (slab_span).  So
** every box that contains the triangle is entered no later than t and left
** no earlier: pruning by the closest t so far is exact, in the BVH and in
** the top-level walk over batching points.  The true distance lies in that
** interval, so the clamp only removes rounding.  Returns 0 for a
** degenerate triangle (cross product exactly 0 in double: it never hits)
** or an empty interval (the ray misses the box, so the "hit" was
** rounding), and at once when the box's interval misses [tnear, tfar]
** (the clamped t could not lie in the segment: the same answer, sooner).
** A ray all but in the triangle's plane is the exception: the plane gives
** no distance then (0/0, or any t), the edge test's verdict is rounding's,
** and the box clamp alone would put the hit anywhere in the box, voxels
** away from the triangle, where no proxy covers it (test: svdag:
** instances: the proxy is entered no later than any instance hit).  So the
** interval is narrowed to the span in which the ray lies in the
** triangle's prism grown by PAD_REL of the largest |coordinate| of the
** corners and the origin (prism_span), when that span meets the box's:
** the hit's point then lies within that grow of the triangle, which the
** proxies' margin covers (svdag.c, "CONSERVATIVE IN FLOAT").  A ray that
** crosses the plane inside the triangle has its true distance inside the
** grown prism, so for it this changes nothing; and no hit becomes a miss
** (watertightness is the edge test's).  So the prism is skipped when the
** edge functions' signs are certain (each beyond its error bound:
** edges_certain), which makes the exact crossing an inner point:
** most hits, at the cost of a few compares (make bench-embree times it). */
static int hit_distance(const tri_ray *r, const brt_ray_prep *bp, const float *p0,
                        const float *p1, const float *p2, float woop_t, float tnear, float tfar,
                        const woop_values *wv, float *t)
{
    double e1[3], e2[3], w[3], n[3], td, prism_lo, prism_hi, reach = 0;
    float lo[3], hi[3], plo[3], phi[3], entry, exit, tt;
    int a;
    for (a = 0; a < 3; a++) {
        e1[a] = (double)p1[a] - p0[a];
        e2[a] = (double)p2[a] - p0[a];
        w[a] = (double)p0[a] - r->org[a];
        lo[a] = p0[a] < p1[a] ? p0[a] : p1[a];
        lo[a] = p2[a] < lo[a] ? p2[a] : lo[a];
        hi[a] = p0[a] > p1[a] ? p0[a] : p1[a];
        hi[a] = p2[a] > hi[a] ? p2[a] : hi[a];
    }
    n[0] = e1[1] * e2[2] - e1[2] * e2[1];
    n[1] = e1[2] * e2[0] - e1[0] * e2[2];
    n[2] = e1[0] * e2[1] - e1[1] * e2[0];
    if (n[0] == 0.0 && n[1] == 0.0 && n[2] == 0.0) return 0;
    td = (n[0] * w[0] + n[1] * w[1] + n[2] * w[2]) /
         (n[0] * r->dir[0] + n[1] * r->dir[1] + n[2] * r->dir[2]);
    tt = isfinite(td) ? (float)td : woop_t;
    brt_box_pad(lo, hi, plo, phi);
    if (!slab_span(bp, plo, phi, -INFINITY, INFINITY, &entry, &exit)) return 0;
    if (entry > tfar || exit < tnear) return 0;   /* t lies in [entry, exit]: no hit in the segment */
    if (!edges_certain(wv)) {
        for (a = 0; a < 3; a++) {
            reach = fmax(reach, fabs((double)r->org[a]));
            reach = fmax(reach, fmax(fabs((double)lo[a]), fabs((double)hi[a])));
        }
        if (prism_span(w, e1, e2, n, r->dir, (double)PAD_REL * reach, &prism_lo, &prism_hi) &&
            prism_lo <= exit && prism_hi >= entry) {
            if (prism_lo > entry) entry = (float)prism_lo;
            if (prism_hi < exit) exit = (float)prism_hi;
            if (entry > exit) entry = exit;     /* the float rounding of a point-like span */
        }
    }
    *t = tt < entry ? entry : (tt > exit ? exit : tt);
    return 1;
}

/* BEHIND THE SEGMENT, decided early.  A bounce ray leaves a surface, so
** the line through it crosses the triangle it left just behind its
** origin: the edge test (a line test) passes, and only the final t
** rejects it, after hit_distance's double plane and box.  Woop's own t,
** T/det in float, is known first, and Pharr, Jakob and Humphreys (PBR 3rd
** ed., 3.9.6, "Conservative ray-triangle t") bound its distance from the
** exact t* of the line and the plane by deltaT, from the magnitudes of
** the sheared coordinates and edge functions (our arithmetic is theirs:
** the same translation, permutation, shear and sum).  When
** t_woop + 2 deltaT < tnear, t* < tnear - deltaT, and so:
**   - the box interval's entry is at most t* (the clamp's interval holds
**     the true distance: hit_distance), so below tnear;
**   - float(td), the plane in double rounded once, lies within deltaT of t*
**     (double carries 29 bits more than the float bound assumes), so it
**     is below tnear too;
** and the clamped t would be below tnear: hit_distance would reject it.
** The bound is evaluated in double, and a NaN or inf (a det of 0 or
** overflow) never rejects.  So the answers are unchanged, only sooner
** (tests: bvh: behind the segment compares every answer with the early
** rejection on and off; callgrind on build/trace over bounce rays counts
** the instructions it spares). */
#define GAMMA(n) ((n) * 0x1p-24 / (1.0 - (n) * 0x1p-24))

#ifdef BRT_TESTING
static int early_reject = 1;   /* testing.h: brt_test_early_reject */
static uint64_t node_visits;   /* testing.h: brt_test_node_visits, while */
static int counting_nodes;     /* counting_nodes (brt_test_count_bottom) */
#define NODE_VISITED() do { if (counting_nodes) node_visits++; } while (0)
#else
enum { early_reject = 1 };     /* a constant: the walks always reject early */
#define NODE_VISITED() ((void)0)
#endif

static double max_abs3f(float a, float b, float c)
{
    double m = fabs((double)a);
    if (fabs((double)b) > m) m = fabs((double)b);
    if (fabs((double)c) > m) m = fabs((double)c);
    return m;
}

/* The bound on the error of the float edge functions eu, ev, ew against
** the exact ones (PBR 3.9.6's de, with gradual underflow's term). */
static inline double edge_error(float ax, float ay, float bx, float by, float cx, float cy,
                                float zs0, float zs1, float zs2)
{
    const double max_z = max_abs3f(zs0, zs1, zs2), max_x = max_abs3f(ax, bx, cx);
    const double max_y = max_abs3f(ay, by, cy);
    const double dx = GAMMA(5) * (max_x + max_z) + 0x1p-148, dy = GAMMA(5) * (max_y + max_z) + 0x1p-148;
    return 2.0 * (GAMMA(2) * max_x * max_y + dy * max_x + dx * max_y) + 0x1p-147;
}

/* Whether the float edge functions' signs are the exact ones, each farther
** from 0 than edge_error: the exact line then crosses the triangle inside
** it, and hit_distance's prism cannot move t. */
static inline int edges_certain(const woop_values *wv)
{
    const double de = edge_error(wv->ax, wv->ay, wv->bx, wv->by, wv->cx, wv->cy, wv->zs0, wv->zs1, wv->zs2);
    return fabs((double)wv->eu) > de && fabs((double)wv->ev) > de && fabs((double)wv->ew) > de;
}

/* 1 when the float hit distance t_woop, of Woop's values, certainly lies
** more than its error bound below tnear (see above).  The gammas bound
** relative errors, which hold while no float result is subnormal; each
** bound therefore also carries the absolute error of gradual underflow
** (at most 2^-150 per rounded operation, a few 2^-149 in all), and a
** subnormal det, whose reciprocal loses its relative accuracy, or an
** infinite t_woop (1/det overflowing: a ray of subnormal direction
** components, given a finite tnear) never rejects (tests: the fuzz
** corpus's crash-batched-differs-from-direct rays, clipped by layer 10 of
** batchrt.c to a finite tnear). */
static inline int behind_segment(float ax, float ay, float bx, float by, float cx, float cy,
                                 float zs0, float zs1, float zs2, float eu, float ev, float ew,
                                 float det, float t_woop, float tnear)
{
    const double max_z = max_abs3f(zs0, zs1, zs2), max_e = max_abs3f(eu, ev, ew);
    const double dz = GAMMA(3) * max_z + 0x1p-149;
    const double de = edge_error(ax, ay, bx, by, cx, cy, zs0, zs1, zs2);
    const double dt_det = 3.0 * (GAMMA(3) * max_e * max_z + de * max_z + dz * max_e) + 0x1p-146;
    if (!isfinite(t_woop) || !(fabsf(det) >= FLT_MIN)) return 0;
    /* t_woop + 2 dt < tnear with dt = dt_det / |det|, multiplied out: a
    ** division would cost every candidate its latency. */
    return ((double)t_woop - (double)tnear) * fabs((double)det) + 2.0 * dt_det < 0.0;
}

#ifdef BRT_TESTING
void brt_test_early_reject(int on) { early_reject = on; }
uint64_t brt_test_node_visits(void) { return node_visits; }
void brt_test_count_nodes(int on) { counting_nodes = on != 0; }
#endif

/* The watertight test proper (Woop et al., Fig. 4 with culling off).
** Forced inline: as a call, its eleven arguments are passed at every leaf
** triangle (callgrind on build/bench_bvh counts the instructions).
** early: reject triangles behind the segment before hit_distance
** (behind_segment; the walks pass 1, a constant). */
static inline ALWAYS_INLINE int tri_intersect(const tri_ray *r, const brt_ray_prep *bp,
                                const float *p0, const float *p1, const float *p2,
                                float tnear, float tfar,
                                float *t, float *u, float *v, int early)
{
    const int kx = r->kx, ky = r->ky, kz = r->kz;
    const float az = p0[kz] - r->org[kz], bz = p1[kz] - r->org[kz];
    const float cz = p2[kz] - r->org[kz];
    const float ax = (p0[kx] - r->org[kx]) - r->sx * az;
    const float ay = (p0[ky] - r->org[ky]) - r->sy * az;
    const float bx = (p1[kx] - r->org[kx]) - r->sx * bz;
    const float by = (p1[ky] - r->org[ky]) - r->sy * bz;
    const float cx = (p2[kx] - r->org[kx]) - r->sx * cz;
    const float cy = (p2[ky] - r->org[ky]) - r->sy * cz;
    float eu = cx * by - cy * bx;
    float ev = ax * cy - ay * cx;
    float ew = bx * ay - by * ax;
    float det, tt, rcp;

    /* An edge function of exactly 0 may be a rounding artefact: redo all
    ** three in double so shared edges are decided consistently.  Their
    ** signs are read in double: a product of two floats is exact there,
    ** but a value below half float's smallest subnormal (the sheared
    ** coordinates of a ray all but in the triangle's plane, with a
    ** subnormal shear) would round to a 0 that reads as "on the edge",
    ** and a triangle the ray passes beside would report a hit. */
    if (eu == 0.0f || ev == 0.0f || ew == 0.0f) {
        const double du = (double)cx * by - (double)cy * bx;
        const double dv = (double)ax * cy - (double)ay * cx;
        const double dw = (double)bx * ay - (double)by * ax;
        if ((du < 0.0 || dv < 0.0 || dw < 0.0) && (du > 0.0 || dv > 0.0 || dw > 0.0)) return 0;
        eu = (float)du;
        ev = (float)dv;
        ew = (float)dw;
    }
    if ((eu < 0.0f || ev < 0.0f || ew < 0.0f) &&
        (eu > 0.0f || ev > 0.0f || ew > 0.0f))
        return 0;
    det = eu + ev + ew;
    if (det == 0.0f) return 0;
    tt = eu * (r->sz * az) + ev * (r->sz * bz) + ew * (r->sz * cz);
    rcp = 1.0f / det;
    if (early && tt * rcp < tnear &&   /* most candidates are not behind: one compare */
        behind_segment(ax, ay, bx, by, cx, cy, r->sz * az, r->sz * bz, r->sz * cz,
                       eu, ev, ew, det, tt * rcp, tnear))
        return 0;
    {
        const woop_values wv = {ax, ay, bx, by, cx, cy, r->sz * az, r->sz * bz, r->sz * cz, eu, ev, ew};
        if (!hit_distance(r, bp, p0, p1, p2, tt * rcp, tnear, tfar, &wv, &tt)) return 0;
    }
    /* A hit has a finite t in the segment (NaN fails the compares too;
    ** an infinite t is the plane equation overflowing float). */
    if (!(tt >= tnear && tt <= tfar) || isinf(tt)) return 0;
    *t = tt;
    *u = ev * rcp;
    *v = ew * rcp;
    return 1;
}

int brt_intersect_triangle(const brt_ray *ray, const float v0[3],
                           const float v1[3], const float v2[3],
                           float *t, float *u, float *v)
{
    tri_ray r;
    brt_ray_prep bp;
    if (!brt_ray_valid(ray)) return 0;
    tri_ray_setup(ray, &r);
    brt_ray_prepare(ray, &bp);
    return tri_intersect(&r, &bp, v0, v1, v2, ray->tnear, ray->tfar, t, u, v, early_reject);
}

/* ---- four slots at once ---- */

/* Entry and exit distance of four boxes given by their near planes nr
** and far planes fr (per axis, four lanes: the rows brt_box_lanes' near_row
** and far_row pick); returns a mask of lanes whose interval meets
** [tnear, tfar] (inclusive).  NaN never narrows.  Each lane is slab_span's
** arithmetic in slab_span's order, so every caller -- the triangle BVHs
** here, the top level in batchrt.c -- gets the same bits for the same box.
** Written lane-wise with the mask bits as a select of constants, so that
** GCC -O2 turns the whole test into vector instructions (a per-lane shift
** loop stays scalar).  The distances go to local arrays first: written
** straight to lo and hi, which might alias the inputs, the loop stays
** scalar in brt_box_span4 (callgrind on build/bench_bvh counts a node's
** instructions). */
static inline ALWAYS_INLINE unsigned box_span4(const brt_box_lanes *b, const float *const nr[3],
                                               const float *const fr[3], float tnear, float tfar,
                                               float lo[4], float hi[4])
{
    static const unsigned lane_bit[4] = {1u, 2u, 4u, 8u};
    float tl[4], th[4];
    unsigned bit[4];
    int i;
    for (i = 0; i < 4; i++) {
        const float x0 = (nr[0][i] - b->org_near[0][i]) * b->inv[0][i];
        const float y0 = (nr[1][i] - b->org_near[1][i]) * b->inv[1][i];
        const float z0 = (nr[2][i] - b->org_near[2][i]) * b->inv[2][i];
        const float x1 = (fr[0][i] - b->org_far[0][i]) * b->inv[0][i];
        const float y1 = (fr[1][i] - b->org_far[1][i]) * b->inv[1][i];
        const float z1 = (fr[2][i] - b->org_far[2][i]) * b->inv[2][i];
        tl[i] = x0 > tnear ? x0 : tnear;
        tl[i] = y0 > tl[i] ? y0 : tl[i];
        tl[i] = z0 > tl[i] ? z0 : tl[i];
        th[i] = x1 < tfar ? x1 : tfar;
        th[i] = y1 < th[i] ? y1 : th[i];
        th[i] = z1 < th[i] ? z1 : th[i];
        bit[i] = tl[i] <= th[i] ? lane_bit[i] : 0u;
    }
    memcpy(lo, tl, sizeof tl);
    memcpy(hi, th, sizeof th);
    return bit[0] | bit[1] | bit[2] | bit[3];
}

/* ---- quantized nodes ---- */

/* One plane of a node's frame: org + q * scale, each operation rounded
** once (-ffp-contract=off), hence non-decreasing in q.  The build, the
** traversal, bounds and the checker all decode through this one
** function, so they all see the same floats. */
static inline float decode_plane(float org, float scale, unsigned q)
{
    return org + (float)q * scale;   /* decode_row: the same, four at once */
}

/* One row of four slots' planes along axis a: decode_plane of each lane,
** written so that GCC -O2 makes it a few vector instructions (a broadcast
** of the row's word, an and, a conversion, a fix-up, three arithmetic
** operations).  Each lane's byte is masked in place, so lane i holds
** q * 2^(8i); read as int32_t (memcpy: exact-width types are two's
** complement) lane 3 is negative when q >= 128, i.e. (q - 256) * 2^24,
** and adding 2^32 there gives q * 2^24 back.  Every step is exact (at
** most 8 significant bits), and the power of two unit[i] brings each lane
** to the float of its byte: the same decode_plane arithmetic after it.
** (A loop that extracts each byte by shifting stays scalar, and shifting
** lane 3 alone down by 8 bits first takes more instructions than this
** fix-up: callgrind on build/bench_bvh counts them.) */
static inline ALWAYS_INLINE void decode_row(const qnode *n, int row, int a, float out[4])
{
    static const uint32_t mask[4] = {0xFFu, 0xFF00u, 0xFF0000u, 0xFF000000u};
    static const float unit[4] = {1.0f, 1.0f / 256.0f, 1.0f / 65536.0f, 1.0f / 16777216.0f};
    const float o = n->org[a], s = n->scale[a];
    const uint32_t w = n->q[row];
    uint32_t m[4];
    int32_t v[4];
    int i;
    for (i = 0; i < 4; i++) m[i] = w & mask[i];
    memcpy(v, m, sizeof v);
    for (i = 0; i < 4; i++) {
        const float f = (float)v[i];
        out[i] = o + ((f + (f < 0.0f ? 4294967296.0f : 0.0f)) * unit[i]) * s;
    }
}

/* The four slots' boxes as brt_box_span4 rows.  Row by row, four lanes
** each, so that GCC -O2 turns each row into a few vector instructions
** (one loop over all 24 planes with row % 3 stays scalar). */
static inline ALWAYS_INLINE void decode_boxes(const qnode *n, float box[6][4])
{
    int a;
    for (a = 0; a < 3; a++) {
        decode_row(n, a, a, box[a]);
        decode_row(n, a + 3, a, box[a + 3]);
    }
}

/* A node's slots: only the entries are wanted (the exits are dead stores
** the compiler drops).  Only the near and far rows the ray needs are
** decoded, picked by their 32-bit words: indexing the decoded floats
** instead made the compiler store all 24 to the stack and load them back.
** Empty slots are masked out by the caller. */
static inline unsigned box_test4(const brt_box_lanes *b, const qnode *n,
                                 float tnear, float tfar, float lo[4])
{
    float nr[3][4], fr[3][4], hi[4];
    const float *const near[3] = {nr[0], nr[1], nr[2]}, *const far[3] = {fr[0], fr[1], fr[2]};
    decode_row(n, b->near_row[0], 0, nr[0]);
    decode_row(n, b->far_row[0], 0, fr[0]);
    decode_row(n, b->near_row[1], 1, nr[1]);
    decode_row(n, b->far_row[1], 1, fr[1]);
    decode_row(n, b->near_row[2], 2, nr[2]);
    decode_row(n, b->far_row[2], 2, fr[2]);
    return box_span4(b, near, far, tnear, tfar, lo, hi);
}

/* box_span4 of four boxes already decoded (rows as decode_boxes gives
** them: min x, y, z, max x, y, z), read in place: the top level's boxes
** and the resident nodes. */
static inline ALWAYS_INLINE unsigned box_rows4(const brt_box_lanes *b, const float box[6][4],
                                               float tnear, float tfar, float lo[4], float hi[4])
{
    const char *const rows = (const char *)box;
    const float *const near[3] = {(const float *)(const void *)(rows + b->near_off[0]),
                                  (const float *)(const void *)(rows + b->near_off[1]),
                                  (const float *)(const void *)(rows + b->near_off[2])};
    const float *const far[3] = {(const float *)(const void *)(rows + b->far_off[0]),
                                 (const float *)(const void *)(rows + b->far_off[1]),
                                 (const float *)(const void *)(rows + b->far_off[2])};
    return box_span4(b, near, far, tnear, tfar, lo, hi);
}

unsigned brt_box_span4(const brt_box_lanes *lanes, const float box[6][4], float tmin,
                       float tmax, float entry[4], float exit[4])
{
    return box_rows4(lanes, box, tmin, tmax, entry, exit);
}

/* The mask of non-empty slots. */
static inline unsigned slot_valid(const qnode *n)
{
    return (unsigned)(n->count[0] != EMPTY_COUNT) | (unsigned)(n->count[1] != EMPTY_COUNT) << 1 |
           (unsigned)(n->count[2] != EMPTY_COUNT) << 2 | (unsigned)(n->count[3] != EMPTY_COUNT) << 3;
}

/* What non-empty slot i points to.  Inner slots come first, then leaves,
** then empty ones (the build orders them so, brt_bvh_blob_open insists),
** so inner slot i is child first_node + i, and leaf slot i starts after the
** triangles of the slots below it (inner slots count 0): arithmetic, not
** a loop over the slots at every node. */
static inline uint32_t slot_target(const qnode *n, unsigned i)
{
    const unsigned below = (i > 0 ? n->count[0] : 0u) + (i > 1 ? n->count[1] : 0u) +
                           (i > 2 ? n->count[2] : 0u);
    return n->count[i] == 0 ? n->first_node + i : n->first_tri + below;
}

/* ===================================================================== */
/* Traversal                                                             */
/* ===================================================================== */

typedef struct stack_entry {
    uint32_t child;
    uint32_t count;   /* > 0: a leaf */
    uint32_t vbase;   /* the leaf's vertex_base */
    float lo;         /* entry distance, for pruning when popped */
} stack_entry;

/* The lowest set bit of a 4-bit mask (C99 has no ctz). */
static const unsigned char lowest_bit[16] = {0, 0, 1, 0, 2, 0, 1, 0, 3, 0, 1, 0, 2, 0, 1, 0};

/* Starts fetching the memory of every slot in mask (a child node's cache
** line, a leaf's vertex indices) before the first is visited: cold rays
** wait on DRAM for nearly every node, and these misses then overlap
** instead of queueing one after another.  A hint only: without GCC's
** builtin (or clang's, which defines __GNUC__ too) it does nothing. */
static void prefetch_slots(const brt_bvh *bvh, const qnode *n, unsigned mask)
{
#if defined(__GNUC__)
    for (; mask != 0; mask &= mask - 1) {
        const unsigned i = lowest_bit[mask];
        if (n->count[i] == 0) __builtin_prefetch(&bvh->nodes[slot_target(n, i)]);
        else __builtin_prefetch(bvh->idx + 3 * (size_t)slot_target(n, i));
    }
#else
    (void)bvh; (void)n; (void)mask;
#endif
}

static inline ALWAYS_INLINE stack_entry slot_entry(const qnode *n, unsigned i, const float lo[4])
{
    stack_entry e;
    e.child = slot_target(n, i);
    e.count = n->count[i];
    e.vbase = n->vertex_base;
    e.lo = lo[i];
    return e;
}

/* Orders the hit slots of a node (mask != 0) by descending entry
** distance into order[], returning how many: the caller pushes all but
** the last (the nearest), which it visits next.  One hit -- most nodes --
** and two take short paths; otherwise an insertion sort of at most four.
** (Equal distances keep slot order in all three.) */
static inline ALWAYS_INLINE int order_slots(unsigned mask, const float lo[4], unsigned order[4])
{
    const unsigned rest = mask & (mask - 1);
    int k = 0, j;
    if (rest == 0) {
        order[0] = lowest_bit[mask];
        return 1;
    }
    if ((rest & (rest - 1)) == 0) {
        const unsigned a = lowest_bit[mask], b = lowest_bit[rest];
        const int swap = lo[a] < lo[b];
        order[0] = swap ? b : a;
        order[1] = swap ? a : b;
        return 2;
    }
    for (; mask != 0; mask &= mask - 1) {
        const unsigned i = lowest_bit[mask];
        for (j = k++; j > 0 && lo[order[j - 1]] < lo[i]; j--) order[j] = order[j - 1];
        order[j] = i;
    }
    return k;
}

/* The next entry of the quantized walk (order_slots); returns the new
** stack size. */
static int next_child(const qnode *n, unsigned mask, const float lo[4],
                      stack_entry *stack, int sp, stack_entry *next)
{
    unsigned order[4];
    const int k = order_slots(mask, lo, order);
    int j;
    for (j = 0; j < k - 1; j++) stack[sp++] = slot_entry(n, order[j], lo);
    *next = slot_entry(n, order[k - 1], lo);
    return sp;
}

/* The three corners of stored triangle k of a leaf whose node has
** vertex_base vbase. */
static void triangle_corners(const brt_bvh *bvh, uint32_t k, uint32_t vbase,
                             const float *p[3])
{
    const uint16_t *ix = bvh->idx + 3 * (size_t)k;
    p[0] = bvh->verts + 3 * ((size_t)vbase + ix[0]);
    p[1] = bvh->verts + 3 * ((size_t)vbase + ix[1]);
    p[2] = bvh->verts + 3 * ((size_t)vbase + ix[2]);
}

/* The geometric normal (v1-v0) x (v2-v0) of a triangle. */
static void triangle_normal(const float *const p[3], float n[3])
{
    int a;
    for (a = 0; a < 3; a++) {
        const int b = (a + 1) % 3, c = (a + 2) % 3;
        n[a] = (p[1][b] - p[0][b]) * (p[2][c] - p[0][c]) - (p[1][c] - p[0][c]) * (p[2][b] - p[0][b]);
    }
}

/* The per-ray state of a walk: the prepared ray, its box and triangle
** constants, and the segment's far end (the closest hit so far). */
/* tri_ray's constants for a block of four triangles: the origin's and
** the shear's components in four lanes, and the byte offsets in a tri4's
** corner of the rows of axes kx, ky, kz (set once per ray, so that a
** block's test only loads). */
typedef struct block_ray {
    float ox[4], oy[4], oz[4], sx[4], sy[4];
    size_t offx, offy, offz;
} block_ray;

typedef struct walk {
    const brt_box_lanes *br;
    block_ray kr;
    const brt_ray_prep *prep;
    tri_ray tr;
    float tnear, tfar;
    uint32_t inst;
    const brt_ray *ray;
    int tri_ready;        /* tr and kr set (at the first leaf: most rays reach few) */
    brt_hit *hit;
    float *normal;
    int any;
} walk;

static void block_ray_setup(const tri_ray *r, block_ray *k)
{
    int i;
    for (i = 0; i < 4; i++) {
        k->ox[i] = r->org[r->kx];
        k->oy[i] = r->org[r->ky];
        k->oz[i] = r->org[r->kz];
        k->sx[i] = r->sx;
        k->sy[i] = r->sy;
    }
    k->offx = (size_t)r->kx * sizeof(float[4]);
    k->offy = (size_t)r->ky * sizeof(float[4]);
    k->offz = (size_t)r->kz * sizeof(float[4]);
}

/* The triangle test's per-ray constants, at a walk's first leaf. */
static inline void walk_leaf(walk *w)
{
    if (w->tri_ready) return;
    tri_ray_setup(w->ray, &w->tr);
    block_ray_setup(&w->tr, &w->kr);
    w->tri_ready = 1;
}

/* Sets a walk of the prepared ray up; 0 when it cannot hit anything
** (invalid, or an empty segment). */
static int walk_begin(walk *w, const brt_ray *ray, const brt_ray_prep *prep,
                      const brt_box_lanes *lanes, uint32_t inst, brt_hit *hit, float normal[3], int any)
{
    if (!prep->valid) return 0;
    w->prep = prep;
    w->br = lanes;
    w->tnear = ray->tnear;
    w->tfar = ray->tfar;
    if (!any && hit->t < w->tfar) w->tfar = hit->t;
    if (!(w->tnear <= w->tfar)) return 0;
    w->ray = ray;
    w->tri_ready = 0;
    w->inst = inst;
    w->hit = hit;
    w->normal = normal;
    w->any = any;
    return 1;
}

/* Whether a popped entry, entered at lo, can be skipped: inclusive, so a
** box entered at exactly the closest hit's t is visited (an equal t with
** a lower number wins). */
static inline int walk_prunes(const walk *w, float lo)
{
    return lo > w->tfar;
}

/* One stored triangle (corners p, reported number prim) in a walk:
** returns 1 when an any-hit walk may stop; a closest-hit walk keeps the
** hit if it is closer (brt_hit_is_closer: ties go to the lower number,
** so the order triangles are met in never matters). */
static inline ALWAYS_INLINE int walk_triangle(walk *w, const float *const p[3], uint32_t prim)
{
    float t, u, v;
    if (!tri_intersect(&w->tr, w->prep, p[0], p[1], p[2], w->tnear, w->tfar, &t, &u, &v, 1))
        return 0;
    if (w->any) return 1;
    if (brt_hit_is_closer(t, w->inst, prim, w->hit)) {
        w->hit->t = t;
        w->hit->prim = prim;
        w->hit->u = u;
        w->hit->v = v;
        w->hit->inst = w->inst;
        w->tfar = t;
        if (w->normal) triangle_normal(p, w->normal);
    }
    return 0;
}

/* ---- leaf blocks: four triangles at once ---- */

/* The lanes of a block that may hold a hit: all but those with a
** negative and a positive edge function, which tri_intersect rejects.
** The edge functions are tri_intersect's arithmetic in its order
** (-ffp-contract=off), so the same bits.  A third edge function of 0
** changes nothing: tri_intersect then redoes all three in double, and
** rounding is monotone (a float product or difference keeps the order
** of the exact values), so a float edge function below or above 0 is so
** in double too, and the signs still mix.  Each remaining lane then runs
** tri_intersect itself, so the answers are its own.  Written lane-wise
** with a select of constants, so GCC -O2 turns it into vector
** instructions (callgrind on build/trace counts them). */
static inline ALWAYS_INLINE const float *block_row(const tri4 *b, int corner, size_t off)
{
    return (const float *)(const void *)((const char *)b->v[corner] + off);
}

static inline ALWAYS_INLINE unsigned tri4_candidates(const block_ray *r, const tri4 *b)
{
    static const unsigned lane_bit[4] = {1u, 2u, 4u, 8u};
    const float *const x0 = block_row(b, 0, r->offx), *const y0 = block_row(b, 0, r->offy);
    const float *const z0 = block_row(b, 0, r->offz), *const x1 = block_row(b, 1, r->offx);
    const float *const y1 = block_row(b, 1, r->offy), *const z1 = block_row(b, 1, r->offz);
    const float *const x2 = block_row(b, 2, r->offx), *const y2 = block_row(b, 2, r->offy);
    const float *const z2 = block_row(b, 2, r->offz);
    unsigned bit[4];
    int i;
    for (i = 0; i < 4; i++) {
        const float az = z0[i] - r->oz[i], bz = z1[i] - r->oz[i], cz = z2[i] - r->oz[i];
        const float ax = (x0[i] - r->ox[i]) - r->sx[i] * az;
        const float ay = (y0[i] - r->oy[i]) - r->sy[i] * az;
        const float bx = (x1[i] - r->ox[i]) - r->sx[i] * bz;
        const float by = (y1[i] - r->oy[i]) - r->sy[i] * bz;
        const float cx = (x2[i] - r->ox[i]) - r->sx[i] * cz;
        const float cy = (y2[i] - r->oy[i]) - r->sy[i] * cz;
        const float eu = cx * by - cy * bx;
        const float ev = ax * cy - ay * cx;
        const float ew = bx * ay - by * ax;
        const int neg = (eu < 0.0f) | (ev < 0.0f) | (ew < 0.0f);
        const int pos = (eu > 0.0f) | (ev > 0.0f) | (ew > 0.0f);
        bit[i] = (neg & pos) ? 0u : lane_bit[i];
    }
    return bit[0] | bit[1] | bit[2] | bit[3];
}

/* How many of a leaf's count triangles the block from its triangle k
** holds: four, but fewer in the last. */
static inline unsigned block_size(uint32_t count, uint32_t k)
{
    return count - k < 4 ? count - k : 4;
}

/* The first n (1..4) triangles of a block in a walk: the filter, then
** tri_intersect on the lanes it keeps; 1 when an any-hit walk may stop. */
static inline ALWAYS_INLINE int block_triangles(walk *w, const tri4 *b, unsigned n)
{
    unsigned m = tri4_candidates(&w->kr, b) & ((1u << n) - 1u);
    for (; m != 0; m &= m - 1) {
        const unsigned i = lowest_bit[m];
        float c[3][3];
        const float *const p[3] = {c[0], c[1], c[2]};
        int k, a;
        for (k = 0; k < 3; k++)
            for (a = 0; a < 3; a++) c[k][a] = b->v[k][a][i];
        if (walk_triangle(w, p, b->prim[i])) return 1;
    }
    return 0;
}

/* Block b filled with the n (1..4) triangles of a leaf from stored
** triangle t0 on (node vertex_base vbase): the corners' bits, the
** reported numbers, and every other byte 0, so that a block is written
** once.  The decode (resident_leaf_copy) and the quantized walk's leaves
** (quantized_leaf) fill blocks alike. */
static void block_fill(const brt_bvh *bvh, uint32_t t0, unsigned n, uint32_t vbase, tri4 *b)
{
    unsigned lane;
    memset(b, 0, sizeof *b);
    for (lane = 0; lane < n; lane++) {
        const float *p[3];
        int j, a;
        triangle_corners(bvh, t0 + lane, vbase, p);
        for (j = 0; j < 3; j++)
            for (a = 0; a < 3; a++) b->v[j][a][lane] = p[j][a];
        b->prim[lane] = bvh->prim[t0 + lane];
    }
}

/* The triangles of a quantized leaf (count of them from stored triangle
** first), four at a time through a block on the stack, as the resident
** walk tests them (the same candidates, the same answers); 1 when an
** any-hit walk may stop.  Why a copy: the block filter rejects most
** triangles for fewer instructions than their own tests. */
static int quantized_leaf(const brt_bvh *bvh, walk *w, uint32_t first, uint32_t count,
                          uint32_t vbase)
{
    uint32_t k;
    walk_leaf(w);
    for (k = 0; k < count; k += 4) {
        const unsigned n = block_size(count, k);
        tri4 b;
        block_fill(bvh, first + k, n, vbase, &b);
        if (block_triangles(w, &b, n)) return 1;
    }
    return 0;
}

/* Closest hit into *hit (and its triangle's normal into normal, unless
** NULL, whenever the hit changes), or (any != 0) returns 1 at the first
** hit: the walk over the quantized nodes (a blob read in place).  Empty
** slots are masked out.  The tree is checked acyclic with depth <=
** MAX_DEPTH at build/open time, so each node is entered at most once and
** the stack (3 entries per level) never overflows. */
static int traverse_quantized(const brt_bvh *bvh, const brt_ray *ray, const brt_ray_prep *prep,
                              const brt_box_lanes *lanes, uint32_t inst, brt_hit *hit,
                              float normal[3], int any)
{
    stack_entry stack[STACK_SIZE], cur;
    walk w;
    float lo[4];
    int sp = 0;

    if (!walk_begin(&w, ray, prep, lanes, inst, hit, normal, any)) return 0;
    cur.child = 0;
    cur.count = 0;
    cur.vbase = 0;
    cur.lo = ray->tnear;
    for (;;) {
        while (cur.count == 0) {
            const qnode *n = &bvh->nodes[cur.child];
            NODE_VISITED();
            const unsigned mask = box_test4(w.br, n, w.tnear, w.tfar, lo) & slot_valid(n);
            if (mask == 0) goto pop;
            prefetch_slots(bvh, n, mask);
            sp = next_child(n, mask, lo, stack, sp, &cur);
        }
        if (quantized_leaf(bvh, &w, cur.child, cur.count, cur.vbase)) return 1;
    pop:
        do {
            if (sp == 0) return 0;
            cur = stack[--sp];
        } while (walk_prunes(&w, cur.lo));
    }
}

/* ---- the resident walk ---- */

/* The blocks of four that a leaf of count triangles takes. */
static uint32_t leaf_blocks(unsigned count) { return (count + 3u) / 4u; }

typedef struct resident_entry {
    uint32_t child;   /* node, or (count > 0) first block */
    uint32_t count;   /* > 0: a leaf of that many triangles */
    float lo;         /* entry distance, for pruning when popped */
} resident_entry;

static inline ALWAYS_INLINE resident_entry resident_slot(const fnode *n, unsigned i,
                                                         const float lo[4])
{
    resident_entry e;
    e.child = n->child[i];
    e.count = n->count[i];
    e.lo = lo[i];
    return e;
}

/* Starts fetching what the visits of the slots in mask read: both cache
** lines of a child node, every line of a leaf's blocks (as prefetch_slots,
** for the resident layout).  A block of 160 bytes starts at a multiple
** of 32, so the lines at its start and 64 and 128 bytes on hold it all.
** Written out per block, not as a loop over the bytes, which would be
** among the walk's largest costs (callgrind on build/bench_bvh counts
** them). */
static inline ALWAYS_INLINE void prefetch_resident(const brt_bvh *bvh, const fnode *n,
                                                   unsigned mask)
{
#if defined(__GNUC__)
    for (; mask != 0; mask &= mask - 1) {
        const unsigned i = lowest_bit[mask];
        if (n->count[i] == 0) {
            const char *p = (const char *)&bvh->fnodes[n->child[i]];
            __builtin_prefetch(p);
            __builtin_prefetch(p + 64);
        } else {
            const tri4 *b = &bvh->blocks[n->child[i]];
            const tri4 *const end = b + leaf_blocks(n->count[i]);
            for (; b < end; b++) {
                __builtin_prefetch(b);
                __builtin_prefetch((const char *)b + 64);
                __builtin_prefetch((const char *)b + 128);
            }
        }
    }
#else
    (void)bvh; (void)n; (void)mask;
#endif
}

/* The triangles of a resident leaf (count of them, from block first);
** 1 when an any-hit walk may stop. */
static int resident_leaf(const brt_bvh *bvh, walk *w, uint32_t first, uint32_t count)
{
    uint32_t k;
    walk_leaf(w);
    for (k = 0; k < count; k += 4)
        if (block_triangles(w, &bvh->blocks[first + k / 4], block_size(count, k))) return 1;
    return 0;
}

/* traverse_quantized's walk over the resident layout: the same slots,
** boxes and triangles, so the same hits (the tie rule is total). */
static int traverse_resident(const brt_bvh *bvh, const brt_ray *ray, const brt_ray_prep *prep,
                             const brt_box_lanes *lanes, uint32_t inst, brt_hit *hit,
                             float normal[3], int any)
{
    resident_entry stack[STACK_SIZE], cur;
    walk w;
    float lo[4], hi[4];
    int sp = 0;

    if (!walk_begin(&w, ray, prep, lanes, inst, hit, normal, any)) return 0;
    cur.child = 0;
    cur.count = 0;
    cur.lo = ray->tnear;
    for (;;) {
        while (cur.count == 0) {
            const fnode *n = &bvh->fnodes[cur.child];
            NODE_VISITED();
            const unsigned mask = box_rows4(w.br, (const float (*)[4])n->box, w.tnear, w.tfar,
                                            lo, hi) & n->valid;
            unsigned order[4];
            int k, j;
            if (mask == 0) goto pop;
            k = order_slots(mask, lo, order);
            /* One hit node slot is read at once (a prefetch gains nothing);
            ** a leaf's blocks are read one after another. */
            if (k > 1 || n->count[order[0]] > 0) prefetch_resident(bvh, n, mask);
            for (j = 0; j < k - 1; j++) stack[sp++] = resident_slot(n, order[j], lo);
            cur = resident_slot(n, order[k - 1], lo);
        }
        if (resident_leaf(bvh, &w, cur.child, cur.count)) return 1;
    pop:
        do {
            if (sp == 0) return 0;
            cur = stack[--sp];
        } while (walk_prunes(&w, cur.lo));
    }
}

/* The walk of either layout for a prepared ray: the resident one when
** the BVH has it. */
static int traverse_prepared(const brt_bvh *bvh, const brt_ray *ray, const brt_ray_prep *prep,
                             const brt_box_lanes *lanes, uint32_t inst, brt_hit *hit,
                             float normal[3], int any)
{
    if (bvh->node_count == 0) return 0;
    if (bvh->fnodes) return traverse_resident(bvh, ray, prep, lanes, inst, hit, normal, any);
    return traverse_quantized(bvh, ray, prep, lanes, inst, hit, normal, any);
}

static int traverse(const brt_bvh *bvh, const brt_ray *ray, uint32_t inst, brt_hit *hit,
                    float normal[3], int any)
{
    brt_ray_prep prep;
    brt_box_lanes lanes;
    if (bvh->node_count == 0) return 0;
    brt_ray_prepare(ray, &prep);   /* checks the ray too: prep.valid */
    box_lanes_of(&prep, &lanes);
    return traverse_prepared(bvh, ray, &prep, &lanes, inst, hit, normal, any);
}

int brt_bvh_walk_prepared(const brt_bvh *bvh, const brt_ray *ray, const brt_ray_prep *prep,
                          const brt_box_lanes *lanes, brt_hit *hit, float normal[3], int any)
{
    return traverse_prepared(bvh, ray, prep, lanes, BRT_NO_INST, hit, normal, any);
}

void brt_bvh_intersect(const brt_bvh *bvh, const brt_ray *ray, brt_hit *hit)
{
    traverse(bvh, ray, BRT_NO_INST, hit, NULL, 0);
}

void brt_bvh_intersect_normal(const brt_bvh *bvh, const brt_ray *ray,
                              brt_hit *hit, float normal[3])
{
    traverse(bvh, ray, BRT_NO_INST, hit, normal, 0);
}

int brt_bvh_occluded(const brt_bvh *bvh, const brt_ray *ray)
{
    return traverse(bvh, ray, BRT_NO_INST, NULL, NULL, 1);
}

/* ===================================================================== */
/* Instances: one level, the ray carried into the prototype               */
/* ===================================================================== */
/*
** As in Embree, an instance is intersected by moving the ray, not the
** triangles: o' = M^-1 (o - d) and dir' = M^-1 dir, each computed in
** double and rounded once to float, and the prototype's BVH is traversed
** with (o', dir').  The transform is affine, so the object ray's parameter
** is the world ray's: the hit's t is the object-space test's t, bit for
** bit, in every mode (one function, brt_instance_intersect, does it).
**
** THE MARGIN.  A box of instances in world space (an instance's box, a
** node of boxes above it, a batching point) is tested with the world
** ray, and pruning by "entry > closest t" must never drop an instance
** whose object-space test would report a closer hit.  The object ray is
** not exactly the world ray moved, so the world point p = o + t' dir of an
** object-space hit at t' may lie outside the instance's world box W (the
** prototype's box B, grown by bvh.c's pads, through the transform in
** double, rounded outwards).  How far (infinity norms, u = 2^-24, k =
** ||M|| ||M^-1|| <= BRT_MAX_CONDITION = 2^10, R = the reach of
** brt_instance_margin, >= |d - c| + max |W - d|, about a centre c):
** (Distances from the origin may be taken from any centre c instead:
** |o - d| <= |o - c| + |d - c|, so a reach of |d - c| + the radius of
** brt_instance_bounds about c serves, and far from the world's origin a
** margin stays as small as the instance's neighbourhood.)
**   1. The rounded object ray differs from the exact one by
**      |o' - o*| <= (u + 2^-50) ||M^-1|| |o - d| (one rounding to float
**      plus the double arithmetic), and likewise dir'.
**   2. The triangle clamp keeps t' inside the slab test's span of the
**      triangle's padded box, whose rounding leaves the object point
**      o' + t' dir' inside B grown by 2 PAD_REL (|B| + |o'|) at most
**      (PAD_REL = 32u: the box pad, the origin pad and 3 roundings).
**   3. p - d = M (o' + t' dir') - M (o' - o*) - t' M (dir' - dir*), so p
**      lies within  k [64u (R + |o - d|) + 1.01 u (|o - d| + t'|dir|)]
**      of W, using |M| |B| <= k R and |M| |o'| <= 1.01 k |o - d|; and
**      t'|dir| = |p - o| <= R + |o - d| + that distance itself.
**   4. With k u <= 2^-14 this solves to a distance below
**      68 k u (|o - c| + R)  <=  margin = 64 FLT_EPSILON k (|o - c| + R)
**      (64 FLT_EPSILON = 128 u: twice the bound, which also covers the
**      float rounding of the margin itself).
** Growing every box of instances by the margin (brt_ray_prepare_margin)
** makes the world point of every object-space hit lie inside the grown
** box, so the box test enters it no later than t' and pruning stays
** exact.  Underflow adds at most ||M|| 2^-149 per coordinate; the reach
** carries ||M|| 2^-100 to cover it.  A scene without instances has
** condition 0 and margin 0: its traversal is bit for bit unchanged.
** The tests (bvh: instances) pit this against brute force on
** translations of 1e6, scales of 1e-3 and 1e3, mirrors and shears.
*/

#define MARGIN_REL (64.0f * FLT_EPSILON)

void brt_ray_prepare_margin(const brt_ray *ray, float margin, brt_ray_prep *prep)
{
    int a;
    brt_ray_prepare(ray, prep);
    if (margin == 0.0f) return;
    for (a = 0; a < 3; a++) {
        /* Rounded away from the origin by nextafter so the grown box is
        ** never smaller than the margin says. */
        const float move = margin;
        prep->org_near[a] = prep->negative[a] ? nextafterf(prep->org_near[a] - move, -INFINITY)
                                              : nextafterf(prep->org_near[a] + move, INFINITY);
        prep->org_far[a] = prep->negative[a] ? nextafterf(prep->org_far[a] + move, INFINITY)
                                             : nextafterf(prep->org_far[a] - move, -INFINITY);
    }
}

float brt_instance_margin(float condition, float reach, const float center[3],
                          const brt_ray *ray)
{
    float far = 0.0f;
    int a;
    if (condition == 0.0f) return 0.0f;
    for (a = 0; a < 3; a++)
        if (fabsf(ray->org[a] - center[a]) > far) far = fabsf(ray->org[a] - center[a]);
    return MARGIN_REL * condition * (far + reach);
}

static double row_sum(const double *m, int row)
{
    return fabs(m[3 * row]) + fabs(m[3 * row + 1]) + fabs(m[3 * row + 2]);
}

static double matrix_norm(const double *m)
{
    double n = row_sum(m, 0);
    if (row_sum(m, 1) > n) n = row_sum(m, 1);
    if (row_sum(m, 2) > n) n = row_sum(m, 2);
    return n;
}

brt_result brt_instance_frame_init(const brt_instance *instance, uint32_t inst,
                                   brt_instance_frame *f, brt_error *err)
{
    double m[9], cof[9], det, cond;
    int i, j;
    for (i = 0; i < 12; i++)
        if (!isfinite(instance->xform[i]))
            return brt_fail(err, BRT_EARG, "instance %u: transform has a non-finite entry",
                            (unsigned)inst);
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++) m[3 * i + j] = instance->xform[4 * i + j];
        f->translation[i] = instance->xform[4 * i + 3];
    }
    /* Cofactors: C_ij = (-1)^(i+j) minor_ij, written cyclically. */
    for (i = 0; i < 3; i++)
        for (j = 0; j < 3; j++) {
            const int i1 = (i + 1) % 3, i2 = (i + 2) % 3, j1 = (j + 1) % 3, j2 = (j + 2) % 3;
            cof[3 * i + j] = m[3 * i1 + j1] * m[3 * i2 + j2] - m[3 * i1 + j2] * m[3 * i2 + j1];
        }
    det = m[0] * cof[0] + m[1] * cof[1] + m[2] * cof[2];
    if (det == 0.0 || !isfinite(det))
        return brt_fail(err, BRT_EARG, "instance %u: transform is singular", (unsigned)inst);
    for (i = 0; i < 3; i++)   /* M^-1 = adj(M) / det, adj = cof^T */
        for (j = 0; j < 3; j++) f->inverse[3 * i + j] = cof[3 * j + i] / det;
    cond = matrix_norm(m) * matrix_norm(f->inverse);
    if (!(cond <= BRT_MAX_CONDITION))
        return brt_fail(err, BRT_EARG,
                        "instance %u: transform's condition number %.4g exceeds %g",
                        (unsigned)inst, cond, BRT_MAX_CONDITION);
    for (i = 0; i < 9; i++) f->cofactor[i] = (float)cof[i];
    /* Rounded up: the margin's bound needs no less. */
    f->condition = nextafterf((float)cond, INFINITY);
    f->norm = nextafterf((float)matrix_norm(m), INFINITY);
    return BRT_OK;
}

void brt_instance_ray(const brt_instance_frame *f, const brt_ray *ray, brt_ray *object_ray)
{
    double w[3];
    int i;
    /* o - d first: an origin near an instance far from the world's origin
    ** keeps its digits (a translation of 1e6). */
    for (i = 0; i < 3; i++) w[i] = (double)ray->org[i] - f->translation[i];
    for (i = 0; i < 3; i++) {
        const double *r = f->inverse + 3 * i;
        object_ray->org[i] = (float)(r[0] * w[0] + r[1] * w[1] + r[2] * w[2]);
        object_ray->dir[i] = (float)(r[0] * ray->dir[0] + r[1] * ray->dir[1] + r[2] * ray->dir[2]);
    }
    object_ray->tnear = ray->tnear;
    object_ray->tfar = ray->tfar;
}

void brt_instance_intersect(const brt_bvh *prototype, const brt_instance_frame *f,
                            uint32_t inst, const brt_ray *ray, brt_hit *hit, float normal[3])
{
    brt_ray object_ray;
    brt_hit before = *hit;
    float n[3];
    int a;
    brt_instance_ray(f, ray, &object_ray);
    traverse(prototype, &object_ray, inst, hit, normal ? n : NULL, 0);
    if (!normal || memcmp(&before, hit, sizeof before) == 0) return;
    /* The world triangle's (v1-v0) x (v2-v0) is cof(M) times the object one. */
    for (a = 0; a < 3; a++)
        normal[a] = f->cofactor[3 * a] * n[0] + f->cofactor[3 * a + 1] * n[1] + f->cofactor[3 * a + 2] * n[2];
}

int brt_instance_occluded(const brt_bvh *prototype, const brt_instance_frame *f,
                          const brt_ray *ray)
{
    brt_ray object_ray;
    brt_instance_ray(f, ray, &object_ray);
    return traverse(prototype, &object_ray, BRT_NO_INST, NULL, NULL, 1);
}

void brt_instance_bounds(const brt_instance *instance, const brt_instance_frame *f,
                         const float obj_lo[3], const float obj_hi[3],
                         float lo[3], float hi[3], float *radius)
{
    double far = 0.0;
    float low[3] = {INFINITY, INFINITY, INFINITY}, high[3] = {-INFINITY, -INFINITY, -INFINITY};
    int corner, a;
    for (a = 0; a < 3; a++) { lo[a] = INFINITY; hi[a] = -INFINITY; }
    if (!(obj_lo[0] <= obj_hi[0])) { *radius = 0.0f; return; }   /* empty prototype */
    for (corner = 0; corner < 8; corner++) {
        double p[3];
        for (a = 0; a < 3; a++) p[a] = (corner >> a & 1) ? obj_hi[a] : obj_lo[a];
        for (a = 0; a < 3; a++) {
            const float *r = instance->xform + 4 * a;
            const double rel = r[0] * p[0] + r[1] * p[1] + r[2] * p[2];
            const float w = (float)(rel + r[3]);
            if (w < low[a]) low[a] = w;
            if (w > high[a]) high[a] = w;
            if (fabs(rel) > far) far = fabs(rel);
        }
    }
    /* float(w) may round inwards: step the extremes outwards once more.
    ** nextafterf is monotone, so stepping the least and the greatest
    ** corner is stepping every corner and keeping the extremes. */
    for (a = 0; a < 3; a++) {
        if (low[a] <= high[a]) {
            lo[a] = nextafterf(low[a], -INFINITY);
            hi[a] = nextafterf(high[a], INFINITY);
        }
    }
    /* A relative 2^-20 covers the rounding of the box outwards; the last
    ** term is the underflow's (see the margin). */
    *radius = nextafterf((float)(far * (1.0 + 0x1p-20) + f->norm * 0x1p-100), INFINITY);
}

/* ---- visiting the boxes (the proxies of instances, svdag.c) ---- */

/* Depth first over the slots of node (a subtree the caller has accepted).
** Recursion is bounded: built and opened trees are at most MAX_DEPTH deep. */
static void visit_node(const brt_bvh *bvh, uint32_t node, brt_bvh_box_fn box,
                       brt_bvh_corner_fn triangle, void *user)
{
    const qnode *n = &bvh->nodes[node];
    float b[6][4];
    unsigned i;
    decode_boxes(n, b);
    for (i = 0; i < 4; i++) {
        const float lo[3] = {b[0][i], b[1][i], b[2][i]}, hi[3] = {b[3][i], b[4][i], b[5][i]};
        uint32_t k;
        if (n->count[i] == EMPTY_COUNT || !box(user, lo, hi)) continue;
        if (n->count[i] == 0) {
            visit_node(bvh, slot_target(n, i), box, triangle, user);
            continue;
        }
        for (k = slot_target(n, i); k < slot_target(n, i) + n->count[i]; k++) {
            const float *p[3];
            triangle_corners(bvh, k, n->vertex_base, p);
            triangle(user, p[0], p[1], p[2]);
        }
    }
}

void brt_bvh_visit(const brt_bvh *bvh, brt_bvh_box_fn box, brt_bvh_corner_fn triangle,
                   void *user)
{
    if (bvh->node_count > 0) visit_node(bvh, 0, box, triangle, user);
}

/* ===================================================================== */
/* Binned SAH build of a binary tree                                     */
/* ===================================================================== */

/* Four lanes, the last unused (0 in triangle boxes), so that growing a
** box is one minps and one maxps at -O2. */
typedef struct aabb {
    float lo[4], hi[4];
} aabb;

/* A triangle during the build: its box and number, permuted in place so
** every pass reads memory in order.  Its centroid is lo + hi (twice the
** box centre, which bins the same). */
typedef struct ref {
    aabb box;
    uint32_t tri;
} ref;

typedef struct bnode {
    aabb box;             /* exact bounds of its triangles */
    uint32_t left, right; /* children; 0 for a leaf (0 is the root) */
    uint32_t first, count;
} bnode;

typedef struct builder {
    ref *refs;            /* leaf order once the build is done */
    bnode *nodes;
    uint32_t node_count;
} builder;

static void aabb_empty(aabb *b)
{
    int a;
    for (a = 0; a < 4; a++) { b->lo[a] = INFINITY; b->hi[a] = -INFINITY; }
}

/* Written as selects, not branches: they compile to minss/maxss. */
static inline void aabb_grow(aabb *b, const aabb *o)
{
    int a;
    for (a = 0; a < 4; a++) {
        b->lo[a] = o->lo[a] < b->lo[a] ? o->lo[a] : b->lo[a];
        b->hi[a] = o->hi[a] > b->hi[a] ? o->hi[a] : b->hi[a];
    }
}

static void aabb_grow_centroid(aabb *b, const aabb *o)
{
    int a;
    for (a = 0; a < 4; a++) {
        const float c = o->lo[a] + o->hi[a];
        b->lo[a] = c < b->lo[a] ? c : b->lo[a];
        b->hi[a] = c > b->hi[a] ? c : b->hi[a];
    }
}

/* Half the surface area; 0 for an empty box. */
static float aabb_area(const aabb *b)
{
    const float dx = b->hi[0] - b->lo[0], dy = b->hi[1] - b->lo[1];
    const float dz = b->hi[2] - b->lo[2];
    if (!(dx >= 0.0f)) return 0.0f;
    return dx * dy + dy * dz + dz * dx;
}

static void range_bounds(const builder *b, uint32_t begin, uint32_t end,
                         aabb *box, aabb *cbox)
{
    uint32_t k;
    aabb_empty(box);
    aabb_empty(cbox);
    for (k = begin; k < end; k++) {
        aabb_grow(box, &b->refs[k].box);
        aabb_grow_centroid(cbox, &b->refs[k].box);
    }
}

/* Maps a centroid to its bins along the three axes of a node. */
typedef struct binning {
    float cmin[4], scale[4];   /* scale 0: the axis cannot be split */
    int bins;                  /* BINS, or fewer for a small node */
} binning;

/* A node of n triangles gets min(n, BINS) bins: the per-node cost of
** the sweep would otherwise dominate the build near the leaves. */
static binning binning_of(const aabb *cbox, uint32_t n)
{
    binning g;
    int a;
    g.bins = n < BINS ? (int)n : BINS;
    for (a = 0; a < 4; a++) {
        const float extent = cbox->hi[a] - cbox->lo[a];
        g.cmin[a] = cbox->lo[a];
        g.scale[a] = a < 3 && extent > 0.0f ? (float)g.bins / extent : 0.0f;
    }
    return g;
}

/* Bins of a triangle along x, y, z (and a dummy 4th lane, so the float
** part is one vector operation); clamped, and NaN-safe (bin 0). */
static inline void bins_of(const binning *g, const ref *r, int bin[4])
{
    float f[4];
    int a;
    for (a = 0; a < 4; a++) {
        f[a] = (r->box.lo[a] + r->box.hi[a] - g->cmin[a]) * g->scale[a];
        f[a] = f[a] > 0.0f ? f[a] : 0.0f;
        f[a] = f[a] < (float)(g->bins - 1) ? f[a] : (float)(g->bins - 1);
    }
    for (a = 0; a < 4; a++) bin[a] = (int)f[a];
}

typedef struct split {
    int axis, bin;        /* left side: bins < bin */
    float cost;           /* SAH cost, in units of the parent's area */
} split;

/* Sweeps the bins of one axis from both ends for the cheapest plane. */
static void sweep_axis(const aabb *bin_box, const uint32_t *bin_count,
                       int bins, int axis, split *best)
{
    float left_area[BINS];
    uint32_t left_count[BINS], n = 0;
    aabb acc;
    int i;
    aabb_empty(&acc);
    for (i = 0; i < bins - 1; i++) {
        aabb_grow(&acc, &bin_box[i]);
        n += bin_count[i];
        left_count[i] = n;
        left_area[i] = aabb_area(&acc);
    }
    aabb_empty(&acc);
    n = 0;
    for (i = bins - 1; i > 0; i--) {
        float cost;
        aabb_grow(&acc, &bin_box[i]);
        n += bin_count[i];
        if (left_count[i - 1] == 0 || n == 0) continue;
        cost = left_area[i - 1] * (float)left_count[i - 1] + aabb_area(&acc) * (float)n;
        if (cost < best->cost) { best->axis = axis; best->bin = i; best->cost = cost; }
    }
}

/* One pass over the triangles bins all three axes. */
static split find_split(const builder *b, uint32_t begin, uint32_t end,
                        const binning *g)
{
    aabb bin_box[3][BINS];
    uint32_t bin_count[3][BINS];
    split best = {-1, 0, INFINITY};
    uint32_t k;
    int a, i;
    for (a = 0; a < 3; a++)
        for (i = 0; i < g->bins; i++) { aabb_empty(&bin_box[a][i]); bin_count[a][i] = 0; }
    for (k = begin; k < end; k++) {
        int bin[4];
        bins_of(g, &b->refs[k], bin);
        for (a = 0; a < 3; a++) {
            aabb_grow(&bin_box[a][bin[a]], &b->refs[k].box);
            bin_count[a][bin[a]]++;
        }
    }
    for (a = 0; a < 3; a++)
        if (g->scale[a] > 0.0f) sweep_axis(bin_box[a], bin_count[a], g->bins, a, &best);
    return best;
}

/* Partitions [begin, end) by the split, computing the children's boxes
** on the way; returns the first right index. */
static uint32_t partition_refs(builder *b, uint32_t begin, uint32_t end,
                               const binning *g, const split *s, aabb child[2][2])
{
    uint32_t i = begin, j = end;
    aabb_empty(&child[0][0]); aabb_empty(&child[0][1]);
    aabb_empty(&child[1][0]); aabb_empty(&child[1][1]);
    while (i < j) {
        const ref r = b->refs[i];
        int bin[4], right;
        bins_of(g, &r, bin);
        right = bin[s->axis] >= s->bin;
        aabb_grow(&child[right][0], &r.box);
        aabb_grow_centroid(&child[right][1], &r.box);
        if (!right) { i++; continue; }
        b->refs[i] = b->refs[--j];
        b->refs[j] = r;
    }
    return i;
}

/* Builds the subtree of [begin, end), whose box and centroid box are
** given; returns its node index. */
static uint32_t build_node(builder *b, uint32_t begin, uint32_t end,
                           const aabb *box, const aabb *cbox, int depth)
{
    const uint32_t index = b->node_count++;
    const uint32_t count = end - begin;
    bnode *node = &b->nodes[index];
    aabb child[2][2];   /* [left/right][box/centroid box] */
    uint32_t mid = begin;
    node->box = *box;
    node->left = node->right = 0;
    node->first = begin;
    node->count = count;
    if (count == 1) return index;
    if (depth < SAH_DEPTH) {
        const binning g = binning_of(cbox, count);
        const split s = find_split(b, begin, end, &g);
        const float area = aabb_area(box);
        const float split_cost = area > 0.0f ? C_TRAV + C_ISECT * s.cost / area : INFINITY;
        if (count <= MAX_LEAF && (s.axis < 0 || C_ISECT * (float)count <= split_cost))
            return index;
        if (s.axis >= 0) mid = partition_refs(b, begin, end, &g, &s, child);
    }
    /* Equal centroids or too deep: halving keeps the depth bound. */
    if (mid == begin || mid == end) {
        mid = begin + count / 2;
        range_bounds(b, begin, mid, &child[0][0], &child[0][1]);
        range_bounds(b, mid, end, &child[1][0], &child[1][1]);
    }
    {
        const uint32_t left = build_node(b, begin, mid, &child[0][0], &child[0][1], depth + 1);
        const uint32_t right = build_node(b, mid, end, &child[1][0], &child[1][1], depth + 1);
        node = &b->nodes[index];
        node->left = left;
        node->right = right;
        node->count = 0;
    }
    return index;
}

/* ===================================================================== */
/* Collapse into the 4-wide quantized layout                             */
/* ===================================================================== */

/* The stored boxes are padded with brt_box_pad, like every box tested. */
static aabb aabb_padded(const aabb *box)
{
    aabb p = *box;
    brt_box_pad(box->lo, box->hi, p.lo, p.hi);
    return p;
}

/* The frame of a node along each axis: org = the lowest plane of its
** slots' padded boxes, and a scale with org + 255 * scale >= the highest
** plane: the rounded quotient, grown by a doubling step until that holds
** (rounding can leave it a few ulps short; the doubling bounds the loop
** even when org dwarfs the extent).  Padded boxes stay within +-FLT_MAX
** (brt_box_pad), so org is finite and no plane decodes to NaN. */
static void set_frame(qnode *w, const aabb *u)
{
    int a;
    for (a = 0; a < 3; a++) {
        /* hi / 255 - lo / 255: no overflow between +-FLT_MAX; 255 * s may
        ** still round to +inf, which only makes the top planes +inf. */
        float s = u->hi[a] / 255.0f - u->lo[a] / 255.0f, step;
        if (s < FLT_MIN) s = FLT_MIN;   /* also a zero extent: planes stay distinct */
        step = s * FLT_EPSILON > FLT_MIN ? s * FLT_EPSILON : FLT_MIN;
        w->org[a] = u->lo[a];
        for (; decode_plane(u->lo[a], s, 255) < u->hi[a]; step *= 2.0f) s += step;
        w->scale[a] = s;
    }
}

/* Rounding OUTWARD: the largest q whose plane is <= v (q = 0 always
** qualifies, its plane is org), and the smallest q whose plane is >= v
** (q = 255 always qualifies).  Binary searches, valid because
** decode_plane is non-decreasing in q; comparisons only, so inf and NaN
** frames cannot trap. */
static unsigned quantize_down(float org, float scale, float v)
{
    unsigned a = 0, b = 255;
    while (a < b) {
        const unsigned mid = (a + b + 1) / 2;
        if (decode_plane(org, scale, mid) <= v) a = mid;
        else b = mid - 1;
    }
    return a;
}

static unsigned quantize_up(float org, float scale, float v)
{
    unsigned a = 0, b = 255;
    while (a < b) {
        const unsigned mid = (a + b) / 2;
        if (decode_plane(org, scale, mid) >= v) b = mid;
        else a = mid + 1;
    }
    return a;
}

/* Slot i's box, quantized in w's frame (set_frame first). */
static void set_slot_box(qnode *w, int i, const aabb *box)
{
    int a;
    for (a = 0; a < 3; a++) {
        w->q[a] |= (uint32_t)quantize_down(w->org[a], w->scale[a], box->lo[a]) << (8 * i);
        w->q[a + 3] |= (uint32_t)quantize_up(w->org[a], w->scale[a], box->hi[a]) << (8 * i);
    }
}

/* The output of the collapse: nodes, then the leaf triangles as they are
** emitted, with their corners shared through a small direct-mapped table
** of recently stored vertices (a table miss only stores a vertex twice,
** which costs bytes, never answers). */
#define VERTEX_TABLE (1u << 16)
#define NO_VERTEX 0xFFFFFFFFu

typedef struct emitter {
    const builder *b;
    const float *positions;
    const uint32_t *indices, *prim_ids;
    qnode *nodes;
    uint32_t node_count, tri_count, vert_count, vert_cap;
    uint16_t *idx;        /* 3 per triangle, relative to the node's vertex_base */
    uint32_t *prim;
    float *verts;         /* grows; at most 3 per triangle */
    uint32_t *recent;     /* VERTEX_TABLE entries: a vertex with that hash */
} emitter;

/* A vertex's slot in the table: a multiplicative hash of its bits (the
** three 32-bit primes of xxHash32, then a fold of the high half), not
** brt_mix64, batchrt's one mixer: a slot holds one vertex, so the slots
** decide which corners a blob shares and which it stores twice, and so
** every blob's bytes.  Like brt_checksum64's steps, these are fixed by
** the scene files written. */
static uint32_t vertex_hash(const float *p)
{
    uint32_t w[3], h;
    memcpy(w, p, sizeof w);
    h = w[0] * 0x9E3779B1u ^ w[1] * 0x85EBCA77u ^ w[2] * 0xC2B2AE3Du;
    return (h ^ (h >> 16)) & (VERTEX_TABLE - 1);
}

/* The index of a vertex with p's exact bits at or after base, stored
** now if the table knows none; NO_VERTEX when out of memory.  Equal bits
** are the same float values, so sharing never changes a triangle. */
static uint32_t vertex_index(emitter *e, const float *p, uint32_t base)
{
    const uint32_t h = vertex_hash(p);
    const uint32_t j = e->recent[h];
    if (j < e->vert_count && j >= base && memcmp(e->verts + 3 * (size_t)j, p, 12) == 0)
        return j;
    if (e->vert_count == e->vert_cap) {
        size_t cap = e->vert_cap;
        float *v = brt_grow(e->verts, &cap, (size_t)e->vert_count + 1, 12);
        if (!v) return NO_VERTEX;
        e->verts = v;
        e->vert_cap = cap < 0xFFFFFFFEu ? (uint32_t)cap : 0xFFFFFFFEu;   /* uint32 numbers */
    }
    memcpy(e->verts + 3 * (size_t)e->vert_count, p, 12);
    e->recent[h] = e->vert_count;
    return e->vert_count++;
}

/* Appends the triangles of binary leaf c, their corners indexed from
** base; 0 when out of memory. */
static int emit_leaf(emitter *e, const bnode *c, uint32_t base)
{
    uint32_t k;
    int j;
    for (k = c->first; k < c->first + c->count; k++) {
        const uint32_t t = e->b->refs[k].tri, out = e->tri_count++;
        for (j = 0; j < 3; j++) {
            const uint32_t v = vertex_index(e, e->positions + 3 * (size_t)e->indices[3 * (size_t)t + j], base);
            if (v == NO_VERTEX) return 0;
            e->idx[3 * (size_t)out + j] = (uint16_t)(v - base);
        }
        e->prim[out] = e->prim_ids ? e->prim_ids[t] : t;
    }
    return 1;
}

/* Picks the (up to four) binary nodes that become the slots of a wide
** node: opens the largest-area inner child until there are four (as
** Embree does).  Returns how many. */
static int wide_slots(const builder *b, uint32_t bi, uint32_t slot[4])
{
    const bnode *root = &b->nodes[bi];
    int n = 0, i;
    if (root->count > 0) slot[n++] = bi;
    else { slot[n++] = root->left; slot[n++] = root->right; }
    while (n < 4) {
        int open = -1;
        float best = -1.0f;
        for (i = 0; i < n; i++) {
            const bnode *c = &b->nodes[slot[i]];
            if (c->count == 0 && aabb_area(&c->box) > best) { best = aabb_area(&c->box); open = i; }
        }
        if (open < 0) break;
        slot[n++] = b->nodes[slot[open]].right;
        slot[open] = b->nodes[slot[open]].left;
    }
    return n;
}

/* Orders a node's slots inner first, then leaves (slot_target's rule);
** stable, so the area order of the rest stays. */
static void inner_first(const builder *b, uint32_t slot[4], int n)
{
    uint32_t sorted[4];
    int i, k = 0, pass;
    for (pass = 0; pass < 2; pass++)
        for (i = 0; i < n; i++)
            if ((b->nodes[slot[i]].count > 0) == (pass == 1)) sorted[k++] = slot[i];
    memcpy(slot, sorted, (size_t)n * sizeof *slot);
}

/* Fills wide node w from binary node bi.  Its inner children get
** consecutive indices after everything emitted so far (so they follow
** their parent and sit together in memory), its leaves' triangles are
** appended in slot order, and its vertex_base is chosen so that every
** vertex it may add (at most NODE_NEW_VERTICES) gets a 16-bit offset:
** older vertices below the base are stored again.  0 when out of
** memory. */
static int emit_wide(emitter *e, uint32_t bi, uint32_t w)
{
    const builder *b = e->b;
    qnode *out = &e->nodes[w];
    uint32_t slot[4], first;
    aabb box[4], frame;
    const int n = wide_slots(b, bi, slot);
    int i, inner = 0;
    inner_first(b, slot, n);
    memset(out, 0, sizeof *out);
    aabb_empty(&frame);
    for (i = 0; i < n; i++) {
        box[i] = aabb_padded(&b->nodes[slot[i]].box);
        aabb_grow(&frame, &box[i]);
    }
    set_frame(out, &frame);
    out->first_node = first = e->node_count;
    out->first_tri = e->tri_count;
    out->vertex_base = e->vert_count > VERTEX_WINDOW - NODE_NEW_VERTICES
                     ? e->vert_count - (VERTEX_WINDOW - NODE_NEW_VERTICES) : 0;
    for (i = 0; i < 4; i++) out->count[i] = EMPTY_COUNT;
    for (i = 0; i < n; i++) {
        const bnode *c = &b->nodes[slot[i]];
        set_slot_box(out, i, &box[i]);
        out->count[i] = (uint8_t)c->count;
        if (c->count == 0) inner++;
        else if (!emit_leaf(e, c, out->vertex_base)) return 0;
    }
    e->node_count += (uint32_t)inner;
    for (i = 0; i < n; i++)
        if (b->nodes[slot[i]].count == 0 && !emit_wide(e, slot[i], first++)) return 0;
    return 1;
}

/* ===================================================================== */
/* Build, free, queries                                                  */
/* ===================================================================== */

static uint64_t arrays_bytes(uint64_t node_count, uint64_t vert_count, uint64_t tri_count)
{
    return node_count * sizeof(qnode) + vert_count * 12u + tri_count * 10u;
}

/* Points the arrays into mem, in the blob's order: nodes, vertices,
** prim ids, vertex indices (each array then starts aligned for its type). */
static void bvh_point(brt_bvh *bvh, const void *mem, uint32_t node_count,
                      uint32_t vert_count, uint32_t tri_count)
{
    const char *p = mem;
    bvh->node_count = node_count;
    bvh->vert_count = vert_count;
    bvh->tri_count = tri_count;
    bvh->nodes = (const qnode *)(const void *)p;
    p += (size_t)node_count * sizeof(qnode);
    bvh->verts = (const float *)(const void *)p;
    p += (size_t)vert_count * 12u;
    bvh->prim = (const uint32_t *)(const void *)p;
    p += (size_t)tri_count * 4u;
    bvh->idx = (const uint16_t *)(const void *)p;
}

/* One allocation for all arrays, copied from the emitter. */
static brt_bvh *bvh_from_emitter(const emitter *e)
{
    const size_t bytes = (size_t)arrays_bytes(e->node_count, e->vert_count, e->tri_count);
    brt_bvh *bvh = calloc(1, sizeof *bvh);
    char *mem = NULL;
    void *m = NULL;
    /* 64-byte alignment: a node is then one cache line. */
    if (bytes && posix_memalign(&m, 64, bytes) != 0) m = NULL;
    if (!bvh || (bytes && !m)) { free(bvh); free(m); return NULL; }
    if (!m) return bvh;   /* the empty BVH: no arrays */
    mem = m;
    bvh->owned = m;
    memcpy(mem, e->nodes, (size_t)e->node_count * sizeof(qnode));
    mem += (size_t)e->node_count * sizeof(qnode);
    memcpy(mem, e->verts, (size_t)e->vert_count * 12u);
    mem += (size_t)e->vert_count * 12u;
    memcpy(mem, e->prim, (size_t)e->tri_count * 4u);
    mem += (size_t)e->tri_count * 4u;
    memcpy(mem, e->idx, (size_t)e->tri_count * 6u);
    bvh_point(bvh, m, e->node_count, e->vert_count, e->tri_count);
    return bvh;
}

/* ---- the resident layout, decoded from the quantized one ---- */

/* Copies leaf slot s of node n into the blocks from first on
** (block_fill, four triangles a block). */
static void resident_leaf_copy(const brt_bvh *bvh, const qnode *n, unsigned s, tri4 *first)
{
    const unsigned count = n->count[s];
    const uint32_t t0 = slot_target(n, s);
    unsigned k;
    for (k = 0; k < count; k += 4)
        block_fill(bvh, t0 + k, block_size(count, k), n->vertex_base, first + k / 4);
}

/* Writes node i of the resident layout and the blocks of its leaves from
** block *next on (advanced past them), every byte (unused slots and
** lanes 0), so that the memory is written once.  The boxes are
** decode_boxes' floats, so every box test sees the planes the quantized
** walk decodes, bit for bit; the corners are the stored vertices' bits. */
static void resident_node(const brt_bvh *bvh, uint32_t i, fnode *f, tri4 *blocks,
                          uint32_t *next)
{
    const qnode *n = &bvh->nodes[i];
    uint32_t at = *next;
    unsigned s;
    decode_boxes(n, f->box);
    f->valid = slot_valid(n);
    f->zero[0] = f->zero[1] = 0;
    for (s = 0; s < 4; s++) {
        f->count[s] = n->count[s];
        f->child[s] = 0;
        if (!(f->valid >> s & 1u)) continue;
        if (n->count[s] == 0) { f->child[s] = slot_target(n, s); continue; }
        f->child[s] = at;
        resident_leaf_copy(bvh, n, s, &blocks[at]);
        at += leaf_blocks(n->count[s]);
    }
    *next = at;
}

static uint32_t resident_block_count(const brt_bvh *bvh)
{
    uint32_t i, blocks = 0;
    unsigned s;
    for (i = 0; i < bvh->node_count; i++)
        for (s = 0; s < 4; s++)
            if ((slot_valid(&bvh->nodes[i]) >> s & 1u) && bvh->nodes[i].count[s] > 0)
                blocks += leaf_blocks(bvh->nodes[i].count[s]);
    return blocks;
}

/* The resident layout of a quantized BVH, in one 64-byte aligned
** allocation (nodes, then blocks); NULL when out of memory. */
static fnode *resident_layout(const brt_bvh *bvh, uint32_t *block_count)
{
    const uint32_t blocks = resident_block_count(bvh);
    const size_t bytes = (size_t)bvh->node_count * sizeof(fnode) + (size_t)blocks * sizeof(tri4);
    void *m = NULL;
    fnode *f;
    uint32_t i, next = 0;
    if (posix_memalign(&m, 64, bytes) != 0) return NULL;
    f = m;
    for (i = 0; i < bvh->node_count; i++)
        resident_node(bvh, i, &f[i], (tri4 *)(void *)(f + bvh->node_count), &next);
    *block_count = blocks;
    return f;
}

/* Adds the resident layout to a quantized BVH; 0 when out of memory. */
static int make_resident(brt_bvh *bvh)
{
    if (bvh->node_count == 0 || bvh->fnodes) return 1;
    bvh->fnodes = resident_layout(bvh, &bvh->block_count);
    bvh->blocks = bvh->fnodes ? (tri4 *)(void *)(bvh->fnodes + bvh->node_count) : NULL;
    return bvh->fnodes != NULL;
}

static size_t resident_bytes(const brt_bvh *bvh)
{
    if (!bvh->fnodes) return 0;
    return (size_t)bvh->node_count * sizeof(fnode) + (size_t)bvh->block_count * sizeof(tri4);
}

size_t brt_bvh_decoded_bytes(const brt_bvh *bvh)
{
    if (bvh->node_count == 0 || bvh->fnodes) return 0;
    return (size_t)bvh->node_count * sizeof(fnode) + (size_t)resident_block_count(bvh) * sizeof(tri4);
}

brt_result brt_bvh_decode(brt_bvh *bvh)
{
    return make_resident(bvh) ? BRT_OK : BRT_ENOMEM;
}

static int setup_refs(builder *b, const float *positions,
                      const uint32_t *indices, uint32_t tri_count)
{
    uint32_t t;
    int a, j;
    for (t = 0; t < tri_count; t++) {
        aabb *box = &b->refs[t].box;
        aabb_empty(box);
        box->lo[3] = box->hi[3] = 0.0f;
        for (j = 0; j < 3; j++) {
            const float *p = positions + 3 * (size_t)indices[3 * (size_t)t + j];
            for (a = 0; a < 3; a++) {
                if (!isfinite(p[a])) return 0;
                if (p[a] < box->lo[a]) box->lo[a] = p[a];
                if (p[a] > box->hi[a]) box->hi[a] = p[a];
            }
        }
        b->refs[t].tri = t;
    }
    return 1;
}

/* The emitter's arrays, sized for the worst case except the vertices
** (which grow: most meshes share each vertex among about six triangles). */
static int emitter_init(emitter *e, const builder *b, const float *positions,
                        const uint32_t *indices, const uint32_t *prim_ids, uint32_t tri_count)
{
    uint32_t i;
    memset(e, 0, sizeof *e);
    e->b = b;
    e->positions = positions;
    e->indices = indices;
    e->prim_ids = prim_ids;
    e->nodes = malloc((2 * (size_t)tri_count - 1) * sizeof *e->nodes);
    e->idx = malloc(3 * (size_t)tri_count * sizeof *e->idx);
    e->prim = malloc((size_t)tri_count * sizeof *e->prim);
    e->vert_cap = tri_count / 2 + NODE_NEW_VERTICES;
    e->verts = malloc(12 * (size_t)e->vert_cap);
    e->recent = malloc(VERTEX_TABLE * sizeof *e->recent);
    if (!e->nodes || !e->idx || !e->prim || !e->verts || !e->recent) return 0;
    for (i = 0; i < VERTEX_TABLE; i++) e->recent[i] = NO_VERTEX;
    e->node_count = 1;
    return 1;
}

static void emitter_free(emitter *e)
{
    free(e->nodes); free(e->idx); free(e->prim); free(e->verts); free(e->recent);
}

brt_result brt_bvh_build(const float *positions, const uint32_t *indices,
                         uint32_t tri_count, const uint32_t *prim_ids,
                         brt_bvh **out)
{
    builder b;
    emitter e;
    aabb box, cbox;
    brt_result r = BRT_ENOMEM;
    *out = NULL;
    if (tri_count > 0 && (!positions || !indices)) return BRT_EARG;
    if (tri_count == 0) {
        *out = calloc(1, sizeof **out);
        return *out ? BRT_OK : BRT_ENOMEM;
    }
    memset(&b, 0, sizeof b);
    b.refs = malloc((size_t)tri_count * sizeof *b.refs);
    b.nodes = malloc((2 * (size_t)tri_count - 1) * sizeof *b.nodes);
    if (!emitter_init(&e, &b, positions, indices, prim_ids, tri_count) || !b.refs || !b.nodes)
        goto done;
    if (!setup_refs(&b, positions, indices, tri_count)) { r = BRT_EARG; goto done; }
    range_bounds(&b, 0, tri_count, &box, &cbox);
    build_node(&b, 0, tri_count, &box, &cbox, 0);
    if (!emit_wide(&e, 0, 0)) goto done;
    *out = bvh_from_emitter(&e);
    if (*out && !make_resident(*out)) { brt_bvh_free(*out); *out = NULL; }
    if (*out) r = BRT_OK;
done:
    free(b.refs); free(b.nodes);
    emitter_free(&e);
    return r;
}

void brt_bvh_free(brt_bvh *bvh)
{
    if (!bvh) return;
    free(bvh->owned);
    free(bvh->fnodes);
    free(bvh);
}

uint32_t brt_bvh_triangle_count(const brt_bvh *bvh) { return bvh->tri_count; }
const uint32_t *brt_bvh_prim_ids(const brt_bvh *bvh) { return bvh->prim; }

size_t brt_bvh_memory_bytes(const brt_bvh *bvh)
{
    return (size_t)arrays_bytes(bvh->node_count, bvh->vert_count, bvh->tri_count) +
           resident_bytes(bvh);
}

void brt_bvh_bounds(const brt_bvh *bvh, float bmin[3], float bmax[3])
{
    float box[6][4];
    int a, i;
    for (a = 0; a < 3; a++) { bmin[a] = INFINITY; bmax[a] = -INFINITY; }
    if (bvh->node_count == 0) return;
    decode_boxes(&bvh->nodes[0], box);
    for (i = 0; i < 4; i++) {
        if (bvh->nodes[0].count[i] == EMPTY_COUNT) continue;
        for (a = 0; a < 3; a++) {
            if (box[a][i] < bmin[a]) bmin[a] = box[a][i];
            if (box[a + 3][i] > bmax[a]) bmax[a] = box[a + 3][i];
        }
    }
}

/* ===================================================================== */
/* Structure validation (blob open) and the checker                      */
/* ===================================================================== */

/* Marks the triangles of one leaf slot, checking that the range is in
** bounds, that no triangle is in two leaves and that every corner index
** lands in the vertex array.  The message on failure, else NULL. */
static const char *mark_leaf(const brt_bvh *bvh, const qnode *n, uint32_t c, unsigned count,
                             unsigned char *seen)
{
    uint32_t k;
    int j;
    if (count > MAX_LEAF || c >= bvh->tri_count || count > bvh->tri_count - c)
        return "bad leaf range";
    for (k = c; k < c + count; k++) {
        if (seen[k]) return "a triangle in two leaves";
        seen[k] = 1;
        for (j = 0; j < 3; j++)
            if ((uint64_t)n->vertex_base + bvh->idx[3 * (size_t)k + j] >= bvh->vert_count)
                return "vertex index out of range";
    }
    return NULL;
}

/* Indices in range, children after parents and referenced once (so the
** nodes form one tree), depth <= MAX_DEPTH, every triangle in exactly one
** leaf, slot counts 0 (inner), 1..MAX_LEAF (leaf) or EMPTY_COUNT, every
** corner in the vertex array.  Everything traversal relies on to stay in
** bounds and terminate.  (Any frame and box bytes are safe: a NaN plane
** only never narrows.) */
static brt_result validate_structure(const brt_bvh *bvh, brt_result code,
                                     brt_error *err)
{
    unsigned char *depth = NULL, *seen = NULL;
    uint32_t i, k;
    brt_result r = code;
    int s;
    if ((bvh->node_count == 0) != (bvh->tri_count == 0) || bvh->vert_count / 3 > bvh->tri_count)
        return brt_fail(err, code, "bvh: %u nodes and %u vertices for %u triangles",
                        (unsigned)bvh->node_count, (unsigned)bvh->vert_count,
                        (unsigned)bvh->tri_count);
    if (bvh->node_count == 0) return BRT_OK;
    depth = calloc(bvh->node_count, 1);
    seen = calloc(bvh->tri_count, 1);
    if (!depth || !seen) { r = brt_fail(err, BRT_ENOMEM, "bvh: out of memory"); goto done; }
    depth[0] = 1;
    for (i = 0; i < bvh->node_count; i++) {
        const qnode *n = &bvh->nodes[i];
        uint32_t c = n->first_node, t = n->first_tri;
        int kind = 0;   /* 0 inner, 1 leaf, 2 empty: slots may only go up */
        if (depth[i] == 0) { brt_fail(err, code, "bvh: node %u is never referenced", (unsigned)i); goto done; }
        for (s = 0; s < 4; s++) {
            const char *bad;
            const int slot_kind = n->count[s] == 0 ? 0 : n->count[s] == EMPTY_COUNT ? 2 : 1;
            if (slot_kind < kind) {
                brt_fail(err, code, "bvh: node %u slot %d: slots not ordered inner, leaf, empty",
                         (unsigned)i, s);
                goto done;
            }
            kind = slot_kind;
            if (kind == 2) continue;
            if (kind == 0) {
                if (c <= i || c >= bvh->node_count || depth[c] != 0 || depth[i] >= MAX_DEPTH) {
                    brt_fail(err, code, "bvh: node %u slot %d: bad child node %u", (unsigned)i, s, (unsigned)c);
                    goto done;
                }
                depth[c++] = (unsigned char)(depth[i] + 1);
                continue;
            }
            bad = mark_leaf(bvh, n, t, n->count[s], seen);
            if (bad) {
                brt_fail(err, code, "bvh: node %u slot %d: %s (triangles %u+%u)", (unsigned)i, s,
                         bad, (unsigned)t, (unsigned)n->count[s]);
                goto done;
            }
            t += n->count[s];
        }
    }
    for (k = 0; k < bvh->tri_count; k++)
        if (!seen[k]) { brt_fail(err, code, "bvh: triangle %u in no leaf", (unsigned)k); goto done; }
    r = BRT_OK;
done:
    free(depth);
    free(seen);
    return r;
}

/* The checker's geometry: every triangle's padded box (the box its hit
** distance is clamped into) lies inside the decoded box of every slot on
** its path from the root.  That is what makes pruning exact (README,
** Floating point, rules 2 and 3): such a slot is entered no later and
** left no earlier than any hit on the triangle.  clip is the
** intersection of the decoded boxes above node i (exact min/max, no
** rounding), so one containment test per triangle covers its whole path. */
static brt_result check_node(const brt_bvh *bvh, uint32_t i, const aabb *clip, brt_error *err)
{
    const qnode *n = &bvh->nodes[i];
    uint32_t k;
    float box[6][4];
    const unsigned valid = slot_valid(n);
    int s, a;
    decode_boxes(n, box);
    for (s = 0; s < 4; s++) {
        aabb c = *clip;
        brt_result r;
        if (!(valid >> s & 1u)) continue;
        for (a = 0; a < 3; a++) {
            c.lo[a] = box[a][s] > c.lo[a] ? box[a][s] : c.lo[a];
            c.hi[a] = box[a + 3][s] < c.hi[a] ? box[a + 3][s] : c.hi[a];
        }
        if (n->count[s] == 0) {
            r = check_node(bvh, slot_target(n, (unsigned)s), &c, err);
            if (r != BRT_OK) return r;
            continue;
        }
        for (k = slot_target(n, (unsigned)s); k < slot_target(n, (unsigned)s) + n->count[s]; k++) {
            const float *p[3];
            aabb t;
            int j;
            triangle_corners(bvh, k, n->vertex_base, p);
            aabb_empty(&t);
            for (j = 0; j < 3; j++)
                for (a = 0; a < 3; a++) {
                    t.lo[a] = p[j][a] < t.lo[a] ? p[j][a] : t.lo[a];
                    t.hi[a] = p[j][a] > t.hi[a] ? p[j][a] : t.hi[a];
                }
            t = aabb_padded(&t);
            for (a = 0; a < 3; a++)
                if (!(c.lo[a] <= t.lo[a] && t.hi[a] <= c.hi[a]))
                    return brt_fail(err, BRT_ECHECK, "bvh: node %u slot %d: triangle %u (prim %u) "
                                    "outside a box on its path", (unsigned)i, s, (unsigned)k,
                                    (unsigned)bvh->prim[k]);
        }
    }
    return BRT_OK;
}

/* The checker of the resident layout: it must be exactly what
** resident_layout makes of the quantized nodes (checked just before),
** every byte, padding and unused lanes (zero) included -- so its boxes
** are the decoded quantized ones and contain what those contain, and its
** slots reach the same triangles. */
static brt_result check_resident(const brt_bvh *bvh, brt_error *err)
{
    uint32_t blocks = 0, i;
    fnode *want = resident_layout(bvh, &blocks);
    const tri4 *want_blocks = want ? (const tri4 *)(const void *)(want + bvh->node_count) : NULL;
    brt_result r = BRT_OK;
    if (!want) return brt_fail(err, BRT_ENOMEM, "bvh: out of memory");
    if (blocks != bvh->block_count || bvh->blocks != (tri4 *)(void *)(bvh->fnodes + bvh->node_count))
        r = brt_fail(err, BRT_ECHECK, "bvh: resident layout: %u blocks, expected %u",
                     (unsigned)bvh->block_count, (unsigned)blocks);
    for (i = 0; r == BRT_OK && i < bvh->node_count; i++)
        if (memcmp(&want[i], &bvh->fnodes[i], sizeof want[i]) != 0)
            r = brt_fail(err, BRT_ECHECK, "bvh: resident node %u differs from quantized node %u "
                         "decoded", (unsigned)i, (unsigned)i);
    for (i = 0; r == BRT_OK && i < blocks; i++)
        if (memcmp(&want_blocks[i], &bvh->blocks[i], sizeof want_blocks[i]) != 0)
            r = brt_fail(err, BRT_ECHECK, "bvh: resident block %u differs from its leaf's "
                         "triangles", (unsigned)i);
    free(want);
    return r;
}

brt_result brt_bvh_check(const brt_bvh *bvh, brt_error *err)
{
    brt_result r = validate_structure(bvh, BRT_ECHECK, err);
    aabb all;
    int a;
    for (a = 0; a < 4; a++) { all.lo[a] = -INFINITY; all.hi[a] = INFINITY; }
    if (r == BRT_OK && bvh->node_count > 0) r = check_node(bvh, 0, &all, err);
    if (r == BRT_OK && bvh->fnodes) r = check_resident(bvh, err);
    return r;
}

size_t brt_bvh_damage_resident(brt_bvh *bvh, uint64_t at)
{
    const size_t bytes = resident_bytes(bvh);
    if (bytes == 0) return 0;
    ((unsigned char *)bvh->fnodes)[at % bytes] ^= (unsigned char)(1u << (at / bytes % 8));
    return bytes;
}

/* ===================================================================== */
/* Relocatable blob: a 64-byte header {magic, node_count, vert_count,     */
/* tri_count, 0..} then the arrays exactly as in memory (bvh_point's      */
/* order).  Little-endian, like every part of the scene file; the blob is */
/* read in place, so a big-endian host refuses it.  A blob at a 64-byte   */
/* aligned address keeps each node on one cache line.                    */
/* ===================================================================== */

static int host_is_little_endian(void)
{
    const uint32_t one = 1;
    unsigned char b;
    memcpy(&b, &one, 1);
    return b == 1;
}

static uint64_t blob_bytes(uint64_t node_count, uint64_t vert_count, uint64_t tri_count)
{
    return BLOB_HEADER + arrays_bytes(node_count, vert_count, tri_count);
}

size_t brt_bvh_blob_size(const brt_bvh *bvh)
{
    return (size_t)blob_bytes(bvh->node_count, bvh->vert_count, bvh->tri_count);
}

void brt_bvh_blob_write(const brt_bvh *bvh, void *dst)
{
    uint32_t header[BLOB_HEADER / 4] = {0};
    char *p = dst;
    header[0] = BLOB_MAGIC;
    header[1] = bvh->node_count;
    header[2] = bvh->vert_count;
    header[3] = bvh->tri_count;
    memcpy(p, header, sizeof header);
    if (bvh->tri_count == 0) return;   /* and no nodes: nothing to copy */
    memcpy(p + sizeof header, bvh->nodes,   /* the arrays are contiguous */
           (size_t)arrays_bytes(bvh->node_count, bvh->vert_count, bvh->tri_count));
}

/* What traversal takes on trust beyond the structure: every slot box in
** use ordered once decoded (lo <= hi, so no NaN), every vertex
** coordinate finite (brt_bvh_build refuses others), and every reported
** number below prim_limit, so a hit never names a triangle the scene does
** not have (nor BRT_NO_PRIM, the mark of a miss).  Checked once per blob
** open, never per ray.  (Top planes may decode to +inf near FLT_MAX.) */
static brt_result validate_blob_data(const brt_bvh *bvh, uint32_t prim_limit,
                                     brt_error *err)
{
    uint32_t i, k;
    size_t c;
    int s, a;
    for (i = 0; i < bvh->node_count; i++) {
        const unsigned valid = slot_valid(&bvh->nodes[i]);
        float box[6][4];
        decode_boxes(&bvh->nodes[i], box);
        for (s = 0; s < 4; s++)
            for (a = 0; a < 3 && (valid >> s & 1u); a++)
                if (!(box[a][s] <= box[a + 3][s]))
                    return brt_fail(err, BRT_EFORMAT, "bvh blob: node %u slot %d: box inverted "
                                    "or NaN", (unsigned)i, s);
    }
    for (c = 0; c < 3 * (size_t)bvh->vert_count; c++)
        if (!isfinite(bvh->verts[c]))
            return brt_fail(err, BRT_EFORMAT, "bvh blob: vertex %u: coordinate not finite",
                            (unsigned)(c / 3));
    for (k = 0; k < bvh->tri_count; k++)
        if (bvh->prim[k] >= prim_limit)
            return brt_fail(err, BRT_EFORMAT, "bvh blob: triangle %u: number %u not below %u",
                            (unsigned)k, (unsigned)bvh->prim[k], (unsigned)prim_limit);
    return BRT_OK;
}

brt_result brt_bvh_blob_open(const void *blob, size_t size, uint32_t prim_limit,
                             brt_bvh **out, brt_error *err)
{
    uint32_t header[BLOB_HEADER / 4];
    int i;
    brt_bvh *bvh;
    brt_result r;
    *out = NULL;
    if (!host_is_little_endian())
        return brt_fail(err, BRT_EFORMAT, "bvh blob: little-endian, read in place; "
                        "this host is big-endian");
    if (((uintptr_t)blob & 15u) != 0)
        return brt_fail(err, BRT_EARG, "bvh blob: not 16-byte aligned");
    if (size < BLOB_HEADER)
        return brt_fail(err, BRT_EFORMAT, "bvh blob: %zu bytes, shorter than its header", size);
    memcpy(header, blob, sizeof header);
    if (header[0] != BLOB_MAGIC)
        return brt_fail(err, BRT_EFORMAT, "bvh blob: bad magic");
    for (i = 4; i < (int)(BLOB_HEADER / 4); i++)
        if (header[i] != 0) return brt_fail(err, BRT_EFORMAT, "bvh blob: nonzero header padding");
    if (blob_bytes(header[1], header[2], header[3]) != size)
        return brt_fail(err, BRT_EFORMAT, "bvh blob: %zu bytes, expected %llu for %u nodes, "
                        "%u vertices and %u triangles", size,
                        (unsigned long long)blob_bytes(header[1], header[2], header[3]),
                        (unsigned)header[1], (unsigned)header[2], (unsigned)header[3]);
    bvh = calloc(1, sizeof *bvh);
    if (!bvh) return brt_fail(err, BRT_ENOMEM, "bvh blob: out of memory");
    bvh_point(bvh, (const char *)blob + BLOB_HEADER, header[1], header[2], header[3]);
    r = validate_structure(bvh, BRT_EFORMAT, err);
    if (r == BRT_OK) r = validate_blob_data(bvh, prim_limit, err);
    if (r != BRT_OK) { free(bvh); return r; }
    *out = bvh;
    return BRT_OK;
}

