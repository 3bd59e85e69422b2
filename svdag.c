/*
** svdag.c -- conservative voxel proxies: the paper's contribution
** (Molenaar and Eisemann 2020, section 3).
**
** In the order of the file:
**   1. brt_voxelize: conservative triangle/box overlap with the 13-axis
**      separating-axis test of Akenine-Moller (2001), evaluated per voxel
**      of each triangle's bounding box, in double precision in grid-local
**      coordinates with every box grown by a bound on the rounding error.
**   2. brt_svdag_add: the grid becomes a sparse voxel octree, built bottom
**      up, whose nodes are deduplicated against one pool shared by every
**      proxy -- the sparse voxel DAG of Kampe, Sintorn and Assarsson (2013)
**      -- with its checks, decoder and blob for the scene file.
**   3. The ray cast of Laine and Karras (2010) -- octant mirroring, the
**      [1,2] coordinate frame, a parent stack per scale -- adapted to the
**      DAG and made conservative for closed, grown boxes:
**      the frame both casts share, then
**      brt_proxy_raycast_reference: their algorithm as one function, its
**      phases in order (INITIALIZE, PUSH, ADVANCE, POP), written for
**      reading; then
**      brt_proxy_raycast: the fast cast, which the tests hold to the
**      reference bit for bit.
**   4. Beyond the paper: inner proxies (its section 4.3, future work):
**      brt_solids_build, brt_voxelize_inner, brt_inner_occludes -- voxels
**      certainly inside closed geometry, which settle an occlusion ray.
**
** NODE LAYOUT (the pool; also the blob, see brt_svdag_blob_write)
**   leaves[]  uint64 per leaf: a 4x4x4 block of voxels, bit x+4*(y+4*z).
**             The two lowest octree levels are bit masks, as Kampe et al.
**             suggest: a pointer per 2x2x2 block would cost more than it.
**   words[]   interior nodes, one after another, children before parents:
**             word 0  child mask in bits 0..7 (bit c: child c = x+2y+4z
**                     is not empty), bit 8 set when the children are
**                     leaves (the node covers 8^3 voxels), bits 9..26
**                     the node's BOUNDS (below), bits 27.. zero;
**             then one uint32 per child, in child order: a word offset
**             of an interior node, or a leaf index when bit 8 is set.
**   BOUNDS: the box of the node's set voxels, per axis a its first and
**   last eighth of the node's side (3 bits each, at 9 + 6a and 12 + 6a):
**   the ray cast tests it before it descends into the node.  A function
**   of the node's subtree, so equal subtrees still have equal headers;
**   kept in memory only (a blob stores the bits as zero, and opening it
**   computes them again).
**   A node's id is its word offset (leaf index for a leaf).  Bytes: 8 per
**   leaf, 4 + 4 * children per interior node.  Every path from a node to
**   a leaf has the same length, so a node's level (log2 of the voxels it
**   spans per side) is a property of the node: 2 for leaves, 3 for nodes
**   with leaf children, one more per step up.  A grid of res < 4 is
**   stored as one leaf whose block is only partly used.
**
** DEDUPLICATION keeps two open-addressing hash tables (node offsets, leaf
** indices) that live with the pool while proxies are added; a hit in a
** table is confirmed by comparing the whole node, since a hash is not
** equality.  A pool opened from a blob rebuilds them on its first add.
*/
#include "internal.h"
/* The oracles and checkers the library holds for its tests; the hooks
** only when compiled with BRT_TESTING (testing.h). */
#include "testing.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#define LEAF_CHILDREN 0x100u   /* header bit: the children are leaves */
#define HEADER_STORED 0x1FFu   /* what a blob stores: mask and LEAF_CHILDREN */
#define BOUNDS_SHIFT 9         /* the bounds of the node (layout above) */
#define BOUNDS_BITS (0x3FFFFu << BOUNDS_SHIFT)
#define MAX_LEVEL 10           /* res 1024 */

/* ===================================================================== */
/* Bits                                                                   */
/* ===================================================================== */

/* Set bits of a byte, by table (classic macro build): the ray cast counts
** a node's children before the one it descends to. */
#define B2(n) n, n + 1, n + 1, n + 2
#define B4(n) B2(n), B2(n + 1), B2(n + 1), B2(n + 2)
#define B6(n) B4(n), B4(n + 1), B4(n + 1), B4(n + 2)
static const unsigned char popcount_table[256] = {B6(0), B6(1), B6(1), B6(2)};
#undef B2
#undef B4
#undef B6

static unsigned popcount8(unsigned m)
{
    return popcount_table[m & 0xFFu];
}

static unsigned popcount64(uint64_t m)
{
    m = m - ((m >> 1) & 0x5555555555555555ull);
    m = (m & 0x3333333333333333ull) + ((m >> 2) & 0x3333333333333333ull);
    m = (m + (m >> 4)) & 0x0F0F0F0F0F0F0F0Full;
    return (unsigned)((m * 0x0101010101010101ull) >> 56);
}

/* Index of the lowest set bit (de Bruijn multiplication); m != 0. */
static unsigned lowest_bit64(uint64_t m)
{
    static const unsigned char table[64] = {
        0, 1, 48, 2, 57, 49, 28, 3, 61, 58, 50, 42, 38, 29, 17, 4,
        62, 55, 59, 36, 53, 51, 43, 22, 45, 39, 33, 30, 24, 18, 12, 5,
        63, 47, 56, 27, 60, 41, 37, 16, 54, 35, 52, 21, 44, 32, 23, 11,
        46, 26, 40, 15, 34, 20, 31, 10, 25, 14, 19, 9, 13, 8, 7, 6};
    return table[((m & (0 - m)) * 0x03F79D71B4CB0A89ull) >> 58];
}

/* min and max without libm's NaN rules (a call each with -std=c99); the
** callers never pass NaN. */
static double min2(double a, double b) { return a < b ? a : b; }
static double max2(double a, double b) { return a > b ? a : b; }

/* log2 of a resolution 2^k with k = 1..10, or -1 for anything else. */
static int resolution_log2(uint32_t res)
{
    if (res < 2 || res > (1u << MAX_LEVEL) || (res & (res - 1))) return -1;
    return (int)(popcount8(res - 1) + popcount8((res - 1) >> 8));
}

int brt_proxy_res_valid(uint32_t res)
{
    return resolution_log2(res) > 0;
}

/* ===================================================================== */
/* Dense grids                                                            */
/* ===================================================================== */

static size_t grid_words(uint32_t res)
{
    return ((size_t)res * res * res + 63) / 64;
}

static brt_result grid_alloc(brt_grid *grid, uint32_t res,
                             const float origin[3], float cell)
{
    grid->bits = NULL;
    if (resolution_log2(res) < 0) return BRT_EARG;
    grid->bits = (uint64_t *)calloc(grid_words(res), sizeof(uint64_t));
    if (!grid->bits) return BRT_ENOMEM;
    grid->res = res;
    memcpy(grid->origin, origin, sizeof grid->origin);
    grid->cell = cell;
    return BRT_OK;
}

/*
** The frame: origin = bmin exactly (a float already, nothing to round) and
** the smallest float cell with cell * res >= every side.  The side is
** computed in double, where the difference of two floats is exact unless
** their exponents are far apart, and then wrong by at most a relative
** 2^-53; the factor (1 + 2^-50) covers that, and rounding the cell up to a
** float keeps cell * res >= side for the real numbers, so the closed grid
** covers the box exactly.  A box with no extent (a point, a flat axis is
** fine) gets a tiny cell relative to its coordinates so the grid is real.
*/
brt_result brt_grid_init(brt_grid *grid, const float bmin[3],
                         const float bmax[3], uint32_t res)
{
    double side = 0, magnitude = 0, cell_d;
    float cell;
    int i;
    grid->bits = NULL;
    if (resolution_log2(res) < 0) return BRT_EARG;
    for (i = 0; i < 3; i++) {
        if (!isfinite(bmin[i]) || !isfinite(bmax[i]) || !(bmin[i] <= bmax[i]))
            return BRT_EARG;
        side = max2(side, (double)bmax[i] - (double)bmin[i]);
        magnitude = max2(magnitude, max2(fabs(bmin[i]), fabs(bmax[i])));
    }
    if (side == 0) side = max2(magnitude * 0x1p-20, 0x1p-100);
    cell_d = side * (1 + 0x1p-50) / res;
    cell = (float)cell_d;
    if ((double)cell < cell_d) cell = nextafterf(cell, INFINITY);
    if (!isfinite(cell)) return BRT_EARG;
    return grid_alloc(grid, res, bmin, cell);
}

void brt_grid_free(brt_grid *grid)
{
    free(grid->bits);
    grid->bits = NULL;
}

static size_t voxel_index(const brt_grid *grid, uint32_t x, uint32_t y,
                          uint32_t z)
{
    return x + (size_t)grid->res * (y + (size_t)grid->res * z);
}

int brt_grid_get(const brt_grid *grid, uint32_t x, uint32_t y, uint32_t z)
{
    size_t i;
    if (x >= grid->res || y >= grid->res || z >= grid->res) return 0;
    i = voxel_index(grid, x, y, z);
    return (int)((grid->bits[i >> 6] >> (i & 63)) & 1);
}

void brt_grid_set(brt_grid *grid, uint32_t x, uint32_t y, uint32_t z)
{
    size_t i;
    if (x >= grid->res || y >= grid->res || z >= grid->res) return;
    i = voxel_index(grid, x, y, z);
    grid->bits[i >> 6] |= 1ull << (i & 63);
}

uint64_t brt_grid_count(const brt_grid *grid)
{
    uint64_t n = 0;
    size_t i, words = grid_words(grid->res);
    for (i = 0; i < words; i++) n += popcount64(grid->bits[i]);
    return n;
}

/* ===================================================================== */
/* Conservative voxelization (Akenine-Moller 2001)                        */
/* ===================================================================== */

/*
** One separating axis a of a triangle, precomputed: the closed box of
** voxel v (center c) lies on one side when a.c < lo or a.c > hi, where
** [lo, hi] is the triangle's projection widened by the box's radius.
*/
typedef struct sat_axis {
    double a[3];
    double lo, hi;
} sat_axis;

/*
** ROUNDING.  Let L bound every |coordinate| in grid-local units (vertices
** and voxel centres).  (1) A local vertex q = (v - origin) / cell is
** computed from floats with two roundings: |q~ - q| <= 2^-52 L.  Moving
** the vertices by e moves every point of the triangle by at most e per
** coordinate, so testing the computed triangle against boxes grown by
** 2^-52 L keeps every box the exact one touches.  (2) Any axis separates
** correctly if its arithmetic does, so errors in computing a (from q~)
** are harmless; what must hold is the comparison.  a.q (3 products, 2
** sums), a.c, |a|_1 and lo/hi each err by at most 2^-51 |a|_1 (L + 1).
** Adding grow = 2^-44 (L + 1) to the box half-size (radius |a|_1 * grow)
** exceeds the sum of these bounds more than 16 times over, so an axis
** only reports "separated" when the exact triangle and exact closed box
** are separated.  The same grow widens the bounding-box (box-normal) test.
*/
static double triangle_grow(double q[3][3], uint32_t res)
{
    double l = res;
    int k, i;
    for (k = 0; k < 3; k++)
        for (i = 0; i < 3; i++) l = max2(l, fabs(q[k][i]));
    return 0x1p-44 * (l + 1);
}

static void axis_setup(sat_axis *s, double ax, double ay, double az,
                       double q[3][3], double grow)
{
    double p, lo = INFINITY, hi = -INFINITY, radius;
    int k;
    s->a[0] = ax; s->a[1] = ay; s->a[2] = az;
    for (k = 0; k < 3; k++) {
        p = ax * q[k][0] + ay * q[k][1] + az * q[k][2];
        lo = min2(lo, p);
        hi = max2(hi, p);
    }
    radius = (fabs(ax) + fabs(ay) + fabs(az)) * (0.5 + grow);
    s->lo = lo - radius;
    s->hi = hi + radius;
}

/* The triangle normal and the 9 cross products edge x box axis.  Zero
** axes (degenerate triangles) never separate, which is what the SAT
** needs: a segment or a point is still tested against the others. */
static void triangle_axes(double q[3][3], double grow, sat_axis axes[10])
{
    double e[3][3];
    int k, i;
    for (k = 0; k < 3; k++)
        for (i = 0; i < 3; i++) e[k][i] = q[(k + 1) % 3][i] - q[k][i];
    axis_setup(&axes[0], e[0][1] * e[1][2] - e[0][2] * e[1][1],
               e[0][2] * e[1][0] - e[0][0] * e[1][2],
               e[0][0] * e[1][1] - e[0][1] * e[1][0], q, grow);
    for (k = 0; k < 3; k++) {
        axis_setup(&axes[1 + 3 * k], 0, e[k][2], -e[k][1], q, grow);
        axis_setup(&axes[2 + 3 * k], -e[k][2], 0, e[k][0], q, grow);
        axis_setup(&axes[3 + 3 * k], e[k][1], -e[k][0], 0, q, grow);
    }
}

/* Voxel range [*first, *last] on one axis touched by [lo, hi] grown; 0
** when it misses the grid.  Clamped in double before converting. */
static int voxel_range(double lo, double hi, double grow, uint32_t res,
                       uint32_t *first, uint32_t *last)
{
    double a = ceil(lo - grow) - 1, b = floor(hi + grow);
    if (!(b >= 0) || !(a <= res - 1.0)) return 0;
    *first = (uint32_t)max2(a, 0);
    *last = (uint32_t)min2(b, res - 1.0);
    return 1;
}

static int box_touches_triangle(const sat_axis axes[10], double cx,
                                double cy, double cz)
{
    int k;
    for (k = 0; k < 10; k++) {
        double d = axes[k].a[0] * cx + axes[k].a[1] * cy + axes[k].a[2] * cz;
        if (d < axes[k].lo || d > axes[k].hi) return 0;
    }
    return 1;
}

/* 1 when every voxel of the range [first, last] (per axis, inside the
** grid) is set. */
static int range_all_set(const brt_grid *grid, const uint32_t first[3], const uint32_t last[3])
{
    uint32_t x, y, z;
    for (z = first[2]; z <= last[2]; z++)
        for (y = first[1]; y <= last[1]; y++)
            for (x = first[0]; x <= last[0]; x++) {
                const size_t i = voxel_index(grid, x, y, z);
                if (!((grid->bits[i >> 6] >> (i & 63)) & 1)) return 0;
            }
    return 1;
}

/* extra (voxel units, >= 0) dilates the voxels tested: instances' margin. */
static void voxelize_triangle(brt_grid *grid, double q[3][3], double extra)
{
    uint32_t first[3], last[3], x, y, z;
    double grow = triangle_grow(q, grid->res) + extra;
    sat_axis axes[10];
    int i;
    for (i = 0; i < 3; i++) {
        double lo = min2(q[0][i], min2(q[1][i], q[2][i]));
        double hi = max2(q[0][i], max2(q[1][i], q[2][i]));
        if (!voxel_range(lo, hi, grow, grid->res, &first[i], &last[i])) return;
    }
    /* A box of one voxel needs no more test than its bounding box. */
    if (first[0] == last[0] && first[1] == last[1] && first[2] == last[2]) {
        brt_grid_set(grid, first[0], first[1], first[2]);
        return;
    }
    if (range_all_set(grid, first, last)) return;   /* nothing left to mark */
    triangle_axes(q, grow, axes);
    for (z = first[2]; z <= last[2]; z++)
        for (y = first[1]; y <= last[1]; y++)
            for (x = first[0]; x <= last[0]; x++)
                if (box_touches_triangle(axes, x + 0.5, y + 0.5, z + 0.5))
                    brt_grid_set(grid, x, y, z);
}

/* The one check of a grid frame, a grid's (grid_frame_valid) or a
** proxy's (brt_proxy_check): res a power of two in 2..1024, origin
** finite, cell finite and positive -- what the voxelization and the cast
** divide and scale by. */
static int frame_valid(uint32_t res, const float origin[3], float cell)
{
    return brt_proxy_res_valid(res) && isfinite(origin[0]) && isfinite(origin[1]) &&
           isfinite(origin[2]) && isfinite(cell) && cell > 0;
}

static int grid_frame_valid(const brt_grid *grid)
{
    return grid->bits && frame_valid(grid->res, grid->origin, grid->cell);
}

brt_result brt_voxelize(brt_grid *grid, const float *positions,
                        const uint32_t *indices, uint32_t tri_count)
{
    uint32_t t;
    int k, i;
    if (!grid_frame_valid(grid)) return BRT_EARG;
    for (t = 0; t < tri_count; t++) {
        double q[3][3];
        for (k = 0; k < 3; k++) {
            const float *v = positions + 3 * (size_t)indices[3 * (size_t)t + k];
            for (i = 0; i < 3; i++) {
                if (!isfinite(v[i])) return BRT_EARG;
                q[k][i] = ((double)v[i] - grid->origin[i]) / grid->cell;
            }
        }
        voxelize_triangle(grid, q, 0.0);
    }
    return BRT_OK;
}

/* ---- Instances ---- */
/*
** An instance is voxelized in grid-local units, q = m v + t, where m =
** M / cell and t = (d - origin) / cell are the transform (M, d) taken to
** the grid once, in double.
**
** ROUNDING OF THE TRANSFORM.  Each of m and t is within 2^-52 of its exact
** value, relatively, and q's three products and three sums add at most
** five roundings: a computed q is within 2^-50 B of the exact one, where
** B bounds |t| + |m| |v| (per row) over every vertex v.  The root's boxes
** hold every vertex (brt_bvh_check), so B is taken once from them
** (instance_reach); the SAT's own rounding is covered as for any triangle
** (the note above), and the transform's by adding 2^-44 (B + 1) to the
** grow, 64 times its bound.  A node box goes to the grid by its centre c
** and half-size h: the box [m c + t - |m| h, m c + t + |m| h] holds the
** exactly transformed box, and is computed within 2^-49 b, b = |t| +
** |m| (|c| + h), that box's own bound; 2^-44 (b + 1) covers it.
** The dilation the caller asks for (the batched mode: a share of a voxel,
** which bounds the rounding of a ray's transform into object space for
** every ray the proxy is asked about, batchrt.c "proxy_admits") widens
** every tested voxel, box or triangle, by as much.
**
** PRUNING (INSTANCE_VOXELS_PRUNED).  It marks what the SAT marks for every
** transformed triangle (INSTANCE_VOXELS_EVERY_TRIANGLE, triangle by
** triangle), visiting part of the prototype's BVH.  A node whose box
** touches only voxels that are set already is left: its triangles could
** add none.  A node whose box touches a single voxel lies inside that
** voxel (its grow exceeds its rounding), and so does each of its
** triangles, which the SAT marks: that voxel is marked without
** descending.  Otherwise the visit descends, down to the triangles and
** their SAT, which also skips a triangle whose voxels are all set.  So
** nothing outside the SAT's voxels is marked, and the work follows the
** boundary between set and unset voxels rather than the instanced
** triangles.  make bench-paper prints both modes' effect on the bytes
** read; the tests hold the two modes' grids and an exact model together
** (tests/test_svdag.c, "instances").
*/
typedef struct instance_voxelizer {
    brt_grid *grid;
    double m[3][3], t[3];       /* object space to grid units */
    double box_extra;           /* a node box's grow beyond its rounding: the dilation */
    double triangle_extra;      /* a triangle's: the dilation and the transform's rounding */
    int every_triangle;         /* INSTANCE_VOXELS_EVERY_TRIANGLE: no pruning */
} instance_voxelizer;

static void to_grid(const instance_voxelizer *iv, const float *v, double q[3])
{
    int a;
    for (a = 0; a < 3; a++)
        q[a] = iv->m[a][0] * v[0] + iv->m[a][1] * v[1] + iv->m[a][2] * v[2] + iv->t[a];
}

/* B of the rounding note: the largest |t| + |m| |v| over the box lo..hi. */
static double instance_reach(const instance_voxelizer *iv, const float lo[3], const float hi[3])
{
    double reach = 0;
    int a, j;
    for (a = 0; a < 3; a++) {
        double row = fabs(iv->t[a]);
        for (j = 0; j < 3; j++) row += fabs(iv->m[a][j]) * max2(fabs(lo[j]), fabs(hi[j]));
        reach = max2(reach, row);
    }
    return reach;
}

/* The voxel range of a node box (0 when it misses the grid): its centre
** and half-size taken to the grid, grown by 2^-44 (b + 1) and the
** dilation (the rounding note above). */
static int box_voxel_range(const instance_voxelizer *iv, const float lo[3], const float hi[3],
                           uint32_t first[3], uint32_t last[3])
{
    double c[3], h[3], centre[3], half[3], b = 0, grow;
    int a, j;
    for (j = 0; j < 3; j++) {
        c[j] = 0.5 * ((double)lo[j] + hi[j]);
        h[j] = 0.5 * ((double)hi[j] - lo[j]);
    }
    for (a = 0; a < 3; a++) {
        double row = fabs(iv->t[a]);
        centre[a] = iv->t[a];
        half[a] = 0;
        for (j = 0; j < 3; j++) {
            centre[a] += iv->m[a][j] * c[j];
            half[a] += fabs(iv->m[a][j]) * h[j];
            row += fabs(iv->m[a][j]) * fabs(c[j]);
        }
        b = max2(b, row + half[a]);
    }
    grow = 0x1p-44 * (b + 1) + iv->box_extra;
    for (a = 0; a < 3; a++)
        if (!voxel_range(centre[a] - half[a], centre[a] + half[a], grow, iv->grid->res, &first[a], &last[a]))
            return 0;
    return 1;
}

static int instance_box(void *user, const float lo[3], const float hi[3])
{
    const instance_voxelizer *iv = user;
    uint32_t first[3], last[3];
    if (!box_voxel_range(iv, lo, hi, first, last)) return 0;
    if (iv->every_triangle) return 1;
    if (range_all_set(iv->grid, first, last)) return 0;
    if (first[0] == last[0] && first[1] == last[1] && first[2] == last[2]) {
        brt_grid_set(iv->grid, first[0], first[1], first[2]);
        return 0;
    }
    return 1;
}

#ifdef BRT_TESTING
static int test_counting;        /* testing.h: brt_test_count_instance_triangles */
static uint64_t test_counted;

void brt_test_count_instance_triangles(int on)
{
    test_counting = on;
    test_counted = 0;
}

uint64_t brt_test_instance_triangles(void)
{
    return test_counted;
}
#define COUNT_INSTANCE_TRIANGLE() ((void)(test_counting && test_counted++))
#else
#define COUNT_INSTANCE_TRIANGLE() ((void)0)
#endif

static void instance_triangle(void *user, const float *v0, const float *v1, const float *v2)
{
    const instance_voxelizer *iv = user;
    double q[3][3];
    COUNT_INSTANCE_TRIANGLE();
    to_grid(iv, v0, q[0]);
    to_grid(iv, v1, q[1]);
    to_grid(iv, v2, q[2]);
    voxelize_triangle(iv->grid, q, iv->triangle_extra);
}

brt_result brt_voxelize_instance(brt_grid *grid, const brt_bvh *prototype,
                                 const float xform[12], float dilation, int mode)
{
    instance_voxelizer iv;
    float lo[3], hi[3];
    int a, j;
    if (!grid_frame_valid(grid) || !(dilation >= 0) || !isfinite(dilation)) return BRT_EARG;
    for (a = 0; a < 12; a++)
        if (!isfinite(xform[a])) return BRT_EARG;
    brt_bvh_bounds(prototype, lo, hi);
    if (!(lo[0] <= hi[0])) return BRT_OK;   /* no triangles */
    iv.grid = grid;
    for (a = 0; a < 3; a++) {
        for (j = 0; j < 3; j++) iv.m[a][j] = (double)xform[4 * a + j] / grid->cell;
        iv.t[a] = ((double)xform[4 * a + 3] - grid->origin[a]) / grid->cell;
    }
    iv.box_extra = (double)dilation / grid->cell;
    iv.triangle_extra = iv.box_extra + 0x1p-44 * (instance_reach(&iv, lo, hi) + 1);
    iv.every_triangle = mode == INSTANCE_VOXELS_EVERY_TRIANGLE;
    brt_bvh_visit(prototype, instance_box, instance_triangle, &iv);
    return BRT_OK;
}

/* ===================================================================== */
/* The node pool and its hash index                                       */
/* ===================================================================== */

typedef struct hash_table {
    uint32_t *slots;    /* item + 1; 0 is empty */
    uint32_t cap;       /* power of two */
    uint32_t count;
} hash_table;

struct brt_svdag {
    uint32_t *words;       /* interior nodes (layout at the top) */
    uint32_t word_count;
    size_t word_cap;
    uint64_t *leaves;
    uint32_t leaf_count;
    size_t leaf_cap;
    uint32_t *starts;      /* bit per word: a node starts here */
    uint32_t node_count;   /* interior nodes */
    hash_table nodes, leaf_set;   /* dedup index; empty until needed */
};

static uint32_t node_length(const uint32_t *node)
{
    return 1 + popcount8(node[0] & 0xFFu);
}

static uint64_t node_hash(const uint32_t *node)
{
    uint64_t h = 0x9E3779B97F4A7C15ull;
    uint32_t i, n = node_length(node);
    for (i = 0; i < n; i++) h = brt_mix64(h ^ node[i]);
    return h;
}

/* What a table holds: items of one kind (nodes or leaves) of one pool. */
typedef struct table_kind {
    uint64_t (*hash)(const brt_svdag *dag, uint32_t item);
    int (*same)(const brt_svdag *dag, uint32_t item, const void *key);
} table_kind;

static uint64_t node_item_hash(const brt_svdag *dag, uint32_t item)
{
    return node_hash(dag->words + item);
}

static int node_item_same(const brt_svdag *dag, uint32_t item, const void *key)
{
    const uint32_t *node = (const uint32_t *)key;
    return dag->words[item] == node[0] &&
           memcmp(dag->words + item + 1, node + 1,
                  (node_length(node) - 1) * sizeof(uint32_t)) == 0;
}

static uint64_t leaf_item_hash(const brt_svdag *dag, uint32_t item)
{
    return brt_mix64(dag->leaves[item]);
}

static int leaf_item_same(const brt_svdag *dag, uint32_t item, const void *key)
{
    return dag->leaves[item] == *(const uint64_t *)key;
}

static const table_kind node_kind = {node_item_hash, node_item_same};
static const table_kind leaf_kind = {leaf_item_hash, leaf_item_same};

/* The slot holding an item equal to key, or the empty slot where it
** would go (linear probing; the table is never more than half full). */
static uint32_t *table_probe(const brt_svdag *dag, const hash_table *t,
                             const table_kind *kind, uint64_t hash,
                             const void *key)
{
    uint32_t i = (uint32_t)hash & (t->cap - 1);
    while (t->slots[i] && !kind->same(dag, t->slots[i] - 1, key))
        i = (i + 1) & (t->cap - 1);
    return &t->slots[i];
}

/* Makes room for one more item, doubling and rehashing past half full. */
static brt_result table_reserve(const brt_svdag *dag, hash_table *t,
                                const table_kind *kind)
{
    hash_table bigger;
    uint32_t i;
    if ((uint64_t)(t->count + 1) * 2 <= t->cap) return BRT_OK;
    if (t->cap >= 0x80000000u) return BRT_ENOMEM;
    bigger.cap = t->cap ? t->cap * 2 : 1024;
    bigger.count = t->count;
    bigger.slots = (uint32_t *)calloc(bigger.cap, sizeof(uint32_t));
    if (!bigger.slots) return BRT_ENOMEM;
    for (i = 0; i < t->cap; i++) {
        uint32_t item = t->slots[i];
        if (item) {
            uint32_t j = (uint32_t)kind->hash(dag, item - 1) & (bigger.cap - 1);
            while (bigger.slots[j]) j = (j + 1) & (bigger.cap - 1);
            bigger.slots[j] = item;
        }
    }
    free(t->slots);
    *t = bigger;
    return BRT_OK;
}

static void table_free(hash_table *t)
{
    free(t->slots);
    memset(t, 0, sizeof *t);
}

/* Inserts an existing item; *duplicate is set when an equal one is there. */
static brt_result table_insert(const brt_svdag *dag, hash_table *t,
                               const table_kind *kind, uint32_t item,
                               const void *key, int *duplicate)
{
    uint32_t *slot;
    brt_result r = table_reserve(dag, t, kind);
    if (r != BRT_OK) return r;
    slot = table_probe(dag, t, kind, kind->hash(dag, item), key);
    if (*slot) *duplicate = 1;
    else { *slot = item + 1; t->count++; }
    return BRT_OK;
}

/* Indexes every node and leaf of a structurally valid pool; *duplicate
** tells whether two equal items were found (only the first is indexed). */
static brt_result index_build(const brt_svdag *dag, hash_table *nodes,
                              hash_table *leaves, int *duplicate)
{
    uint32_t o, i;
    brt_result r = BRT_OK;
    *duplicate = 0;
    for (i = 0; i < dag->leaf_count && r == BRT_OK; i++)
        r = table_insert(dag, leaves, &leaf_kind, i, &dag->leaves[i], duplicate);
    for (o = 0; o < dag->word_count && r == BRT_OK; o += node_length(dag->words + o))
        r = table_insert(dag, nodes, &node_kind, o, dag->words + o, duplicate);
    return r;
}

static brt_result ensure_index(brt_svdag *dag)
{
    int duplicate;
    if (dag->nodes.slots || dag->leaf_set.slots) return BRT_OK;
    return index_build(dag, &dag->nodes, &dag->leaf_set, &duplicate);
}

brt_result brt_svdag_create(brt_svdag **out)
{
    *out = (brt_svdag *)calloc(1, sizeof(brt_svdag));
    return *out ? BRT_OK : BRT_ENOMEM;
}

void brt_svdag_free(brt_svdag *dag)
{
    if (!dag) return;
    free(dag->words);
    free(dag->leaves);
    free(dag->starts);
    table_free(&dag->nodes);
    table_free(&dag->leaf_set);
    free(dag);
}

uint32_t brt_svdag_node_count(const brt_svdag *dag)
{
    return dag->node_count + dag->leaf_count;
}

/* The pool itself (nodes, leaves and the node-start bitmap that lets a
** proxy be checked in O(depth)), without the dedup index. */
size_t brt_svdag_memory_bytes(const brt_svdag *dag)
{
    return (size_t)dag->word_count * 4 + (size_t)dag->leaf_count * 8 +
           ((size_t)dag->word_count + 31) / 32 * 4;
}

static int is_node_start(const brt_svdag *dag, uint32_t o)
{
    return o < dag->word_count && ((dag->starts[o >> 5] >> (o & 31)) & 1);
}

/* Grows words (brt_grow) and the start bitmap with it, a bit per word of
** capacity, to hold extra more words.  Offsets are uint32 node ids. */
static brt_result reserve_words(brt_svdag *dag, uint32_t extra)
{
    size_t need = (size_t)dag->word_count + extra, cap = dag->word_cap;
    size_t had = dag->word_cap ? dag->word_cap / 32 + 1 : 0;
    uint32_t *words, *starts;
    if (need <= cap) return BRT_OK;
    if (need > 0xFFFFFFF0u) return BRT_ENOMEM;
    words = (uint32_t *)brt_grow(dag->words, &cap, need, sizeof(uint32_t));
    if (!words) return BRT_ENOMEM;
    dag->words = words;
    starts = (uint32_t *)realloc(dag->starts, (cap / 32 + 1) * sizeof(uint32_t));
    if (!starts) return BRT_ENOMEM;
    memset(starts + had, 0, (cap / 32 + 1 - had) * sizeof(uint32_t));
    dag->starts = starts;
    dag->word_cap = cap;
    return BRT_OK;
}

/* The id of a leaf equal to mask, appended when the pool has none. */
static brt_result intern_leaf(brt_svdag *dag, uint64_t mask, uint32_t *id)
{
    uint32_t *slot;
    brt_result r = table_reserve(dag, &dag->leaf_set, &leaf_kind);
    if (r != BRT_OK) return r;
    slot = table_probe(dag, &dag->leaf_set, &leaf_kind, brt_mix64(mask), &mask);
    if (!*slot) {
        if (dag->leaf_count == dag->leaf_cap) {
            uint64_t *leaves;
            if (dag->leaf_count >= 0x7FFFFFFFu) return BRT_ENOMEM;   /* leaf ids */
            leaves = (uint64_t *)brt_grow(dag->leaves, &dag->leaf_cap, (size_t)dag->leaf_count + 1,
                                          sizeof(uint64_t));
            if (!leaves) return BRT_ENOMEM;
            dag->leaves = leaves;
        }
        dag->leaves[dag->leaf_count] = mask;
        *slot = ++dag->leaf_count;
        dag->leaf_set.count++;
    }
    *id = *slot - 1;
    return BRT_OK;
}

/* The offset of a node equal to node[], appended when the pool has none. */
static brt_result intern_node(brt_svdag *dag, const uint32_t *node, uint32_t *id)
{
    uint32_t *slot, n = node_length(node);
    brt_result r = table_reserve(dag, &dag->nodes, &node_kind);
    if (r == BRT_OK) r = reserve_words(dag, n);
    if (r != BRT_OK) return r;
    slot = table_probe(dag, &dag->nodes, &node_kind, node_hash(node), node);
    if (!*slot) {
        uint32_t o = dag->word_count;
        memcpy(dag->words + o, node, n * sizeof(uint32_t));
        dag->starts[o >> 5] |= 1u << (o & 31);
        dag->word_count += n;
        dag->node_count++;
        *slot = o + 1;
        dag->nodes.count++;
    }
    *id = *slot - 1;
    return BRT_OK;
}

/* ===================================================================== */
/* Node bounds                                                             */
/* ===================================================================== */

/* The first and last set voxel of a leaf (not empty) along axis a: 0..3. */
static void leaf_extent(uint64_t leaf, int a, unsigned *lo, unsigned *hi)
{
    unsigned i, cols = 0;
    for (i = 0; i < 64; i++)
        if ((leaf >> i) & 1u) cols |= 1u << ((i >> (2 * a)) & 3u);
    for (*lo = 0; !((cols >> *lo) & 1u); ++*lo) {}
    for (*hi = 3; !((cols >> *hi) & 1u); --*hi) {}
}

/* The bounds field (layout at the top) of the interior node whose words
** are node[]: a leaf child c spans voxels 4c..4c+3 of the node's 8 (its
** eighths), a node child's eighths are sixteenths of its parent.  Node
** children must lie below limit, leaf children in the pool; others (a
** blob not yet checked) count as empty: the check that follows rejects
** such a pool anyway. */
static uint32_t node_bounds(const brt_svdag *dag, const uint32_t *node, uint32_t limit)
{
    uint32_t field = 0, slot = 1, c;
    unsigned lo[3] = {7, 7, 7}, hi[3] = {0, 0, 0}, a, l, u;
    for (c = 0; c < 8; c++) {
        uint32_t child;
        if (!((node[0] >> c) & 1u)) continue;
        child = node[slot++];
        if ((node[0] & LEAF_CHILDREN) ? child >= dag->leaf_count || !dag->leaves[child]
                                      : child >= limit)
            continue;
        for (a = 0; a < 3; a++) {
            unsigned half = (c >> a) & 1u;
            if (node[0] & LEAF_CHILDREN) {
                leaf_extent(dag->leaves[child], (int)a, &l, &u);
                l += 4 * half;
                u += 4 * half;
            } else {
                uint32_t g = dag->words[child] >> BOUNDS_SHIFT;
                l = (8 * half + ((g >> (6 * a)) & 7u)) >> 1;
                u = (8 * half + ((g >> (6 * a + 3)) & 7u)) >> 1;
            }
            lo[a] = l < lo[a] ? l : lo[a];
            hi[a] = u > hi[a] ? u : hi[a];
        }
    }
    for (a = 0; a < 3; a++) field |= (lo[a] | hi[a] << 3) << (6 * a);
    return field << BOUNDS_SHIFT;
}

/* ===================================================================== */
/* SVO build, bottom up, straight into the DAG                             */
/* ===================================================================== */

/* Levels of a proxy's tree: the root spans 2^levels voxels per side. */
static int tree_levels(uint32_t res)
{
    int k = resolution_log2(res);
    return k < 2 ? 2 : k;
}
/* The 4x4x4 block at (x,y,z) as a leaf mask; each row of 4 voxels is one
** aligned nibble of the grid's bits when res >= 4. */
static uint64_t block_mask(const brt_grid *grid, uint32_t x, uint32_t y,
                           uint32_t z)
{
    uint64_t mask = 0;
    uint32_t dx, dy, dz;
    for (dz = 0; dz < 4; dz++)
        for (dy = 0; dy < 4; dy++) {
            uint64_t row = 0;
            if (grid->res >= 4) {
                size_t i = voxel_index(grid, x, y + dy, z + dz);
                row = (grid->bits[i >> 6] >> (i & 63)) & 15u;
            } else {
                for (dx = 0; dx < 4; dx++)
                    row |= (uint64_t)brt_grid_get(grid, x + dx, y + dy, z + dz) << dx;
            }
            mask |= row << (4 * dy + 16 * dz);
        }
    return mask;
}

/* Builds the subtree of the given level at voxel (x,y,z); *id is
** BRT_EMPTY_ROOT when it holds no voxel. */
static brt_result build_subtree(brt_svdag *dag, const brt_grid *grid,
                                int level, uint32_t x, uint32_t y, uint32_t z,
                                uint32_t *id)
{
    uint32_t node[9], half = 1u << (level - 1), mask = 0, c;
    *id = BRT_EMPTY_ROOT;
    if (level == 2) {
        uint64_t leaf = block_mask(grid, x, y, z);
        return leaf ? intern_leaf(dag, leaf, id) : BRT_OK;
    }
    for (c = 0; c < 8; c++) {
        uint32_t child;
        brt_result r = build_subtree(dag, grid, level - 1, x + (c & 1) * half,
                                     y + ((c >> 1) & 1) * half,
                                     z + (c >> 2) * half, &child);
        if (r != BRT_OK) return r;
        if (child != BRT_EMPTY_ROOT) {
            node[1 + popcount8(mask)] = child;
            mask |= 1u << c;
        }
    }
    if (!mask) return BRT_OK;
    node[0] = mask | (level == 3 ? LEAF_CHILDREN : 0);
    node[0] |= node_bounds(dag, node, dag->word_count);
    return intern_node(dag, node, id);
}

brt_result brt_svdag_add(brt_svdag *dag, const brt_grid *grid,
                         brt_proxy *proxy)
{
    brt_result r;
    if (!grid_frame_valid(grid)) return BRT_EARG;
    r = ensure_index(dag);
    if (r == BRT_OK)
        r = build_subtree(dag, grid, tree_levels(grid->res), 0, 0, 0, &proxy->root);
    if (r != BRT_OK) return r;
    proxy->res = grid->res;
    memcpy(proxy->origin, grid->origin, sizeof proxy->origin);
    proxy->cell = grid->cell;
    return BRT_OK;
}

/* ===================================================================== */
/* Checks, decode, statistics                                              */
/* ===================================================================== */

/* Level of a node of a checked pool: 3 + steps down to leaf children. */
static int node_level(const brt_svdag *dag, uint32_t o)
{
    int level = 3;
    while (!(dag->words[o] & LEAF_CHILDREN) && level <= MAX_LEVEL) {
        o = dag->words[o + 1];
        level++;
    }
    return level;
}

/* A res-2 grid uses only the low 2x2x2 corner of its leaf. */
#define RES2_LEAF_BITS 0x0000000000330033ull

brt_result brt_proxy_check(const brt_svdag *dag, const brt_proxy *proxy,
                           brt_error *err)
{
    int k = resolution_log2(proxy->res);
    if (!frame_valid(proxy->res, proxy->origin, proxy->cell))
        return brt_fail(err, BRT_ECHECK, "svdag: proxy frame res %u, origin %g %g %g, cell %g: "
                        "wants res 2^k (k = 1..10), a finite origin and a finite cell > 0",
                        proxy->res, proxy->origin[0], proxy->origin[1], proxy->origin[2], proxy->cell);
    if (proxy->root == BRT_EMPTY_ROOT) return BRT_OK;
    if (k <= 2) {
        if (proxy->root >= dag->leaf_count)
            return brt_fail(err, BRT_ECHECK, "svdag: proxy root leaf %u out of range", proxy->root);
        if (k == 1 && (dag->leaves[proxy->root] & ~RES2_LEAF_BITS))
            return brt_fail(err, BRT_ECHECK, "svdag: res-2 proxy root leaf has voxels outside the grid");
        return BRT_OK;
    }
    if (!is_node_start(dag, proxy->root) || node_level(dag, proxy->root) != k)
        return brt_fail(err, BRT_ECHECK, "svdag: proxy root %u is not a node of level %d", proxy->root, k);
    return BRT_OK;
}

/* Checks one interior node at offset o whose children are before it;
** records its level. */
static brt_result check_node(const brt_svdag *dag, uint32_t o,
                             unsigned char *levels, brt_error *err)
{
    uint32_t h = dag->words[o], n = popcount8(h & 0xFFu), i;
    int child_level = -1;
    if ((h & ~(HEADER_STORED | BOUNDS_BITS)) || !(h & 0xFFu))
        return brt_fail(err, BRT_ECHECK, "svdag: node %u: bad header 0x%x", o, h);
    if ((uint64_t)o + 1 + n > dag->word_count)
        return brt_fail(err, BRT_ECHECK, "svdag: node %u runs past the pool", o);
    if ((h & BOUNDS_BITS) != node_bounds(dag, dag->words + o, o))
        return brt_fail(err, BRT_ECHECK, "svdag: node %u: wrong bounds in header 0x%x", o, h);
    for (i = 0; i < n; i++) {
        uint32_t c = dag->words[o + 1 + i];
        int level;
        if (h & LEAF_CHILDREN) {
            if (c >= dag->leaf_count)
                return brt_fail(err, BRT_ECHECK, "svdag: node %u: leaf %u out of range", o, c);
            level = 2;
        } else {
            if (c >= o || !levels[c])
                return brt_fail(err, BRT_ECHECK, "svdag: node %u: child %u is not an earlier node", o, c);
            level = levels[c];
        }
        if (child_level >= 0 && level != child_level)
            return brt_fail(err, BRT_ECHECK, "svdag: node %u: children of different depths", o);
        child_level = level;
    }
    if (child_level + 1 > MAX_LEVEL)
        return brt_fail(err, BRT_ECHECK, "svdag: node %u deeper than level %d", o, MAX_LEVEL);
    levels[o] = (unsigned char)(child_level + 1);
    return BRT_OK;
}

static brt_result check_structure(const brt_svdag *dag, unsigned char *levels,
                                  brt_error *err)
{
    uint32_t o, i, nodes = 0;
    brt_result r;
    for (i = 0; i < dag->leaf_count; i++)
        if (!dag->leaves[i])
            return brt_fail(err, BRT_ECHECK, "svdag: leaf %u is empty", i);
    for (o = 0; o < dag->word_count; o += node_length(dag->words + o), nodes++) {
        r = check_node(dag, o, levels, err);
        if (r != BRT_OK) return r;
    }
    if (nodes != dag->node_count)
        return brt_fail(err, BRT_ECHECK, "svdag: %u nodes, %u counted", nodes, dag->node_count);
    for (o = 0; o < dag->word_count; o++)
        if (!levels[o] != !is_node_start(dag, o))
            return brt_fail(err, BRT_ECHECK, "svdag: node-start bitmap wrong at %u", o);
    return BRT_OK;
}

brt_result brt_svdag_check(const brt_svdag *dag, brt_error *err)
{
    hash_table nodes = {NULL, 0, 0}, leaves = {NULL, 0, 0};
    unsigned char *levels = (unsigned char *)calloc((size_t)dag->word_count + 1, 1);
    int duplicate = 0;
    brt_result r;
    if (!levels) return brt_fail(err, BRT_ENOMEM, "svdag: out of memory");
    r = check_structure(dag, levels, err);
    free(levels);
    if (r != BRT_OK) return r;
    r = index_build(dag, &nodes, &leaves, &duplicate);
    table_free(&nodes);
    table_free(&leaves);
    if (r != BRT_OK) return brt_fail(err, r, "svdag: out of memory");
    if (duplicate) return brt_fail(err, BRT_ECHECK, "svdag: two identical nodes");
    return BRT_OK;
}

static void decode_subtree(const brt_svdag *dag, uint32_t id, int level,
                           uint32_t x, uint32_t y, uint32_t z, brt_grid *grid)
{
    uint32_t half = 1u << (level - 1), c, slot = 1;
    if (level == 2) {
        uint64_t mask = dag->leaves[id];
        while (mask) {
            unsigned b = lowest_bit64(mask);
            mask &= mask - 1;
            brt_grid_set(grid, x + (b & 3), y + ((b >> 2) & 3), z + (b >> 4));
        }
        return;
    }
    for (c = 0; c < 8; c++)
        if (dag->words[id] & (1u << c))
            decode_subtree(dag, dag->words[id + slot++], level - 1,
                           x + (c & 1) * half, y + ((c >> 1) & 1) * half,
                           z + (c >> 2) * half, grid);
}

brt_result brt_svdag_decode(const brt_svdag *dag, const brt_proxy *proxy,
                            brt_grid *grid)
{
    brt_result r = brt_proxy_check(dag, proxy, NULL);
    if (r == BRT_OK) r = grid_alloc(grid, proxy->res, proxy->origin, proxy->cell);
    if (r == BRT_OK && proxy->root != BRT_EMPTY_ROOT)
        decode_subtree(dag, proxy->root, tree_levels(proxy->res), 0, 0, 0, grid);
    return r;
}

/* Tree nodes below every pool node, children first (they come earlier). */
uint64_t brt_svdag_svo_nodes(const brt_svdag *dag, const brt_proxy *proxy)
{
    uint64_t *below, n;
    uint32_t o, i;
    if (brt_proxy_check(dag, proxy, NULL) != BRT_OK || proxy->root == BRT_EMPTY_ROOT)
        return 0;
    if (tree_levels(proxy->res) == 2) return 1;
    below = (uint64_t *)malloc(((size_t)dag->word_count + 1) * sizeof(uint64_t));
    if (!below) return 0;
    for (o = 0; o < dag->word_count; o += node_length(dag->words + o)) {
        uint32_t h = dag->words[o];
        below[o] = 1;
        for (i = 0; i < popcount8(h & 0xFFu); i++)
            below[o] += (h & LEAF_CHILDREN) ? 1 : below[dag->words[o + 1 + i]];
    }
    n = below[proxy->root];
    free(below);
    return n;
}

/* ===================================================================== */
/* Blob: the pool for the scene file                                       */
/* ===================================================================== */

/*
** Little-endian (brt_put_le32 and its kin, base.c), no pointers:
**   0  "BRTSVDAG"   8  u32 version (1)   12  u32 word count
**   16 u32 leaf count   20 u32 zero   24 leaves (u64 each)   then words (u32)
** The dedup index is not stored; it is rebuilt if proxies are added later.
*/
#define BLOB_HEADER 24
static const char blob_magic[8] = {'B', 'R', 'T', 'S', 'V', 'D', 'A', 'G'};

size_t brt_svdag_blob_size(const brt_svdag *dag)
{
    return BLOB_HEADER + (size_t)dag->leaf_count * 8 + (size_t)dag->word_count * 4;
}

void brt_svdag_blob_write(const brt_svdag *dag, void *dst)
{
    unsigned char *p = (unsigned char *)dst;
    uint32_t i;
    memcpy(p, blob_magic, 8);
    brt_put_le32(p + 8, 1);
    brt_put_le32(p + 12, dag->word_count);
    brt_put_le32(p + 16, dag->leaf_count);
    brt_put_le32(p + 20, 0);
    p += BLOB_HEADER;
    for (i = 0; i < dag->leaf_count; i++, p += 8) brt_put_le64(p, dag->leaves[i]);
    for (i = 0; i < dag->word_count; i++, p += 4)
        brt_put_le32(p, is_node_start(dag, i) ? dag->words[i] & HEADER_STORED : dag->words[i]);
}

/* Copies the blob's arrays into a new pool and marks node starts by
** walking headers (a corrupt header is caught by the check that follows;
** until then the walk only needs to stay inside the array). */
static brt_result blob_load(const unsigned char *p, uint32_t words,
                            uint32_t leaves, brt_svdag *dag)
{
    uint32_t i, o;
    dag->leaves = (uint64_t *)malloc(((size_t)leaves + 1) * sizeof(uint64_t));
    if (!dag->leaves || reserve_words(dag, words + 1) != BRT_OK) return BRT_ENOMEM;
    dag->leaf_count = dag->leaf_cap = leaves;
    for (i = 0; i < leaves; i++, p += 8) dag->leaves[i] = brt_get_le64(p);
    for (i = 0; i < words; i++, p += 4) dag->words[i] = brt_get_le32(p);
    dag->word_count = words;
    for (o = 0; o < words; o += node_length(dag->words + o)) {
        dag->starts[o >> 5] |= 1u << (o & 31);
        dag->node_count++;
    }
    return BRT_OK;
}

/* Computes the bounds of every node of a pool just loaded, children first;
** 0 when a header has bits that a blob does not store. */
static int blob_bounds(brt_svdag *dag)
{
    uint32_t o;
    for (o = 0; o < dag->word_count; o += node_length(dag->words + o)) {
        if (dag->words[o] & ~HEADER_STORED) return 0;
        if ((uint64_t)o + node_length(dag->words + o) <= dag->word_count)
            dag->words[o] |= node_bounds(dag, dag->words + o, o);
    }
    return 1;
}

brt_result brt_svdag_blob_open(const void *blob, size_t size,
                               brt_svdag **out, brt_error *err)
{
    const unsigned char *p = (const unsigned char *)blob;
    uint64_t words, leaves;
    brt_svdag *dag;
    brt_result r;
    *out = NULL;
    if (size < BLOB_HEADER || memcmp(p, blob_magic, 8) != 0)
        return brt_fail(err, BRT_EFORMAT, "svdag blob: bad magic or too short");
    if (brt_get_le32(p + 8) != 1 || brt_get_le32(p + 20) != 0)
        return brt_fail(err, BRT_EFORMAT, "svdag blob: unknown version");
    words = brt_get_le32(p + 12);
    leaves = brt_get_le32(p + 16);
    if (words >= 0xFFFFFFF0u || leaves > 0x7FFFFFFFu ||
        size != BLOB_HEADER + leaves * 8 + words * 4)
        return brt_fail(err, BRT_EFORMAT, "svdag blob: size %lu does not match its counts",
                        (unsigned long)size);
    r = brt_svdag_create(&dag);
    if (r == BRT_OK) r = blob_load(p + BLOB_HEADER, (uint32_t)words, (uint32_t)leaves, dag);
    if (r != BRT_OK) {
        brt_svdag_free(dag);
        return brt_fail(err, r, "svdag blob: out of memory");
    }
    if (!blob_bounds(dag)) {
        brt_svdag_free(dag);
        return brt_fail(err, BRT_EFORMAT, "svdag blob: a node header has bits above 8 set");
    }
    r = brt_svdag_check(dag, err);
    if (r != BRT_OK) {
        brt_svdag_free(dag);
        return r == BRT_ECHECK ? BRT_EFORMAT : r;
    }
    *out = dag;
    return BRT_OK;
}

/* ===================================================================== */
/* Ray cast (Laine and Karras 2010), conservative: the frame               */
/* ===================================================================== */

/*
** Two casts answer the same question -- the least entry of the segment
** [tnear, tfar] into a set voxel's closed box, grown as below -- and share
** this section: the reference cast (brt_proxy_raycast_reference), their
** algorithm as one function with the paper's phases in order, and the fast
** cast (brt_proxy_raycast), which visits the same voxels in an order of its
** own.  The tests hold the two to the same answers, bit for bit.
**
** THE FRAME.  As in Laine and Karras, the root cube is mapped to [1,2]^3
** and the ray is mirrored so that every direction component is negative
** (octant_mask), so the ray runs towards smaller coordinates and meets a
** cube's upper children first.  Where ESVO reads cube positions out of float
** mantissas, we keep them as the integers those mantissas hold (leaf-voxel
** units, x = 1 + u / N), which is exact in double.  As in ESVO a plane's t
** is a bias minus u times a per-voxel step (tx_bias - x * tx_coef), in
** double; the bias folds in the box growth g of the entry or exit side.
**
** CONSERVATIVE IN FLOAT.  Every box is grown by g on each side, in frame
** units (the root cube has side 1):  g = 2^-18 (P + 3 + A), P = max |p_i|,
** and A = (max |o_i| + max |origin_i|) / (N cell) + 1 bounds the ray
** origin's and the root cube's largest world |coordinate| in frame units.
** - rounding: the world->frame transform errs by a few 2^-53 (P + 1);
**   a plane's t = bias - u * step errs by a few 2^-53 (|bias| + |u step|),
**   which is the t error of moving the plane along its axis by a few
**   2^-53 (P + 3) (divide by |d_i|, the t-per-unit of that axis) < g.
**   A computed slab entry is therefore the exact entry of a plane outside
**   the true box, and max/min are exact: the computed interval is the
**   exact interval of a box containing the true one.
** - near-parallel rays: components below 2^-40 of the largest are replaced
**   by 2^-40 of it (ESVO's epsilon trick, which also handles 0).  Within the
**   root cube |t| <= (P + 2) / max|d|, so the tilted ray stays within
**   2^-40 (P + 2) < g of the true one.  The tilt is towards smaller frame
**   coordinates, as every direction is after mirroring; a zero component
**   of either sign (+0, -0) is not mirrored (d > 0 is false for both).
**   Rays far from the box have a large P, and so a large g: their tilt,
**   proportional to P, stays inside it at any distance.
** - the margin beyond these 2^-40-sized terms (g is 2^22 times larger) is
**   meant for callers that compare with a float ray/triangle test, whose
**   hit point is off by some float ulps of the distance from the ray
**   origin -- a few 2^-24 (P + 3) at most, still well inside g.
** - that test's t, though, is clamped into the triangle's box as the box
**   test pads it (bvh.c, rules 2 and 3), and into the span in which the
**   ray lies in the triangle's prism grown by 2^-19 (max |o_i| + max
**   |box_i|) (bvh.c, hit_distance).  A ray the test calls a hit while it
**   only grazes the triangle (all but in its plane, where the plane gives
**   no distance) so gets a point within that grow of the triangle, plus
**   float ulps of its distance; far from the world's origin that exceeds
**   2^-18 (P + 3).  The term A covers it twice over: 2^-18 A (N cell) >=
**   2^-18 (max |o_i| + max |box_i|), since the triangle's box lies in the
**   root cube.  (Before the prism, such a point could lie anywhere in the
**   box, voxels off the triangle: svdag: instances: the proxy is entered
**   no later than any instance hit found it.)
** The entry is rounded down to float and clamped to tnear.  Rays with a NaN
** or an infinity, zero directions, and a walk that hits the iteration cap
** all answer "hit at tnear", the conservative answer; tnear = tfar is a
** segment of one point, which a box touches or not.  The proxy is not
** checked here (brt_proxy_check, once, when it is built or read).
*/
typedef struct ray_frame {
    double enter_bias[3];   /* t of plane x = 1 grown by +g (entry side) */
    double gap[3];          /* exit minus entry t of one plane: 2g / |d_i| */
    double step[3];         /* t per voxel along each axis: (1/N) / |d_i| */
    unsigned mirror;        /* bit i: axis i mirrored (ESVO's octant_mask) */
    uint32_t bounds_flip;   /* 0x3F at the bounds fields of mirrored axes */
    int levels;             /* root spans N = 2^levels voxels */
    double lo, hi;          /* the live segment: hi shrinks to the best hit */
    int found;              /* a set voxel was touched; its entry is hi */
    int any;                /* stop at the first set voxel: no entry wanted */
} ray_frame;

/* t where the ray enters / leaves the grown slab face at voxel plane u
** (mirrored frame: the ray runs towards smaller u). */
static double enter_t(const ray_frame *r, int axis, uint32_t u)
{
    return r->enter_bias[axis] - u * r->step[axis];
}

static double leave_t(const ray_frame *r, int axis, uint32_t u)
{
    return enter_t(r, axis, u) + r->gap[axis];
}

/* One axis of the frame (frame_setup calls it three times, written out:
** GCC -O2 kept a loop over the axes, counter and all; bench_svdag --scene
** under callgrind measures the cast). */
static void frame_axis(ray_frame *r, int i, double p, double d, double dmax, double g,
                       double unit)
{
    double inv = 1.0 / max2(fabs(d), dmax * 0x1p-40);
    r->enter_bias[i] = (p - (1.0 + g)) * inv;
    r->gap[i] = (p - (1.0 - g)) * inv - r->enter_bias[i];
    r->step[i] = inv * unit;
}

/* A coordinate in the [1,2] frame, mirrored when the direction is positive
** (a select, not a branch). */
static double frame_point(double p, double d)
{
    return d > 0 ? 3.0 - p : p;
}

/* INITIALIZE's frame: ESVO's octant_mask (r->mirror), tx_coef (r->step)
** and tx_bias (r->enter_bias), and the growth g of CONSERVATIVE IN FLOAT. */
static void frame_setup(ray_frame *r, const brt_proxy *proxy, const brt_ray *ray)
{
    double unit, scale, p0, p1, p2, d0, d1, d2, dmax, g, a;
    r->levels = tree_levels(proxy->res);
    unit = 1.0 / (1u << r->levels);                     /* exact */
    scale = unit / proxy->cell;     /* world -> frame; one rounding */
    d0 = ray->dir[0] * scale;
    d1 = ray->dir[1] * scale;
    d2 = ray->dir[2] * scale;
    p0 = frame_point(1.0 + ((double)ray->org[0] - proxy->origin[0]) * scale, d0);
    p1 = frame_point(1.0 + ((double)ray->org[1] - proxy->origin[1]) * scale, d1);
    p2 = frame_point(1.0 + ((double)ray->org[2] - proxy->origin[2]) * scale, d2);
    r->mirror = (unsigned)(d0 > 0) | (unsigned)(d1 > 0) << 1 | (unsigned)(d2 > 0) << 2;
    r->bounds_flip = (0x3Fu & (0u - (r->mirror & 1u))) | (0xFC0u & (0u - ((r->mirror >> 1) & 1u))) |
                     (0x3F000u & (0u - (r->mirror >> 2)));
    dmax = max2(fabs(d0), max2(fabs(d1), fabs(d2)));
    a = (max2(fabs(ray->org[0]), max2(fabs(ray->org[1]), fabs(ray->org[2]))) +
         max2(fabs(proxy->origin[0]), max2(fabs(proxy->origin[1]), fabs(proxy->origin[2])))) * scale + 1;
    g = 0x1p-18 * (max2(fabs(p0), max2(fabs(p1), fabs(p2))) + 3 + a);
    frame_axis(r, 0, p0, d0, dmax, g, unit);
    frame_axis(r, 1, p1, d1, dmax, g, unit);
    frame_axis(r, 2, p2, d2, dmax, g, unit);
    r->found = 0;
}

/* The segment [r->lo, r->hi] clipped to the root cube's grown box (ESVO's
** t_min, t_max of the root); 0 when it misses. */
static int clip_to_root(ray_frame *r)
{
    int a;
    for (a = 0; a < 3; a++) {
        r->lo = max2(r->lo, enter_t(r, a, 1u << r->levels));
        r->hi = min2(r->hi, leave_t(r, a, 0));
    }
    return r->lo <= r->hi;
}

/* Bit o of the result: octant o of a leaf (2x2x2 voxels) is not empty. */
static unsigned leaf_octants(uint64_t leaf)
{
    uint64_t f = leaf | (leaf >> 1);     /* pairs along x, y, z folded onto */
    f |= f >> 4;                         /* the octant's lowest voxel */
    f |= f >> 16;
    return (unsigned)((f & 1u) | ((f >> 1) & 2u) | ((f >> 6) & 4u) | ((f >> 7) & 8u) |
                      ((f >> 28) & 16u) | ((f >> 29) & 32u) | ((f >> 34) & 64u) |
                      ((f >> 35) & 128u));
}

/* The voxels of octant w (world child index) of a leaf, as a 2x2x2 mask
** with bit x + 2y + 4z. */
static uint64_t octant_voxels(uint64_t leaf, unsigned w)
{
    uint64_t m = leaf >> (2 * (w & 1) + 8 * ((w >> 1) & 1) + 32 * (w >> 2));
    return (m & 0x3u) | ((m >> 2) & 0xCu) | ((m >> 12) & 0x30u) | ((m >> 14) & 0xC0u);
}

/* Inlined by force where the compiler allows: GCC -O2 kept child_fetch
** and clip_to_bounds out of line (two call sites each), and the calls
** showed in the fast cast's profile (bench_svdag --scene under
** callgrind). */
#if defined(__GNUC__)
#define WALK_INLINE __attribute__((always_inline)) inline
#else
#define WALK_INLINE inline
#endif

/* Child w (world index, known to be set) of a node of the given level and
** its own world child mask: a pool node, a leaf, an octant's voxels.  So
** the two bit-mask levels of a leaf are walked like any other. */
static WALK_INLINE uint64_t child_fetch(const brt_svdag *dag, uint64_t node, int level,
                            unsigned w, unsigned *m)
{
    uint32_t h, slot;
    uint64_t leaf;
    if (level == 2) {
        *m = (unsigned)octant_voxels(node, w);
        return *m;
    }
    h = dag->words[node];
    slot = dag->words[node + 1 + popcount8(h & ((1u << w) - 1))];
    if (level > 3) {
        *m = dag->words[slot] & 0xFFu;
        return slot;
    }
    leaf = dag->leaves[slot];
    *m = leaf_octants(leaf);
    return leaf;
}

/* brt_ray_valid for the segment [tnear, tfar] of the ray. */
static int cast_valid(const brt_ray *ray, float tnear, float tfar)
{
    brt_ray segment = *ray;
    segment.tnear = tnear;
    segment.tfar = tfar;
    return brt_ray_valid(&segment);
}

/* What both casts do first.  The rays and proxies that need no walk get
** their answer here (0 or 1; *t_entry = tnear); for the rest it sets up
** the frame with the segment [tnear, tfar], the root (a pool node, or a
** leaf when the root spans 4 voxels) and its world child mask, and
** returns -1. */
static int cast_begin(const brt_svdag *dag, const brt_proxy *proxy, const brt_ray *ray,
                      float tnear, float tfar, float *t_entry, ray_frame *r, uint64_t *root,
                      unsigned *m)
{
    if (t_entry) *t_entry = tnear;
    if (tnear > tfar) return 0;                 /* an empty segment holds nothing */
    if (!cast_valid(ray, tnear, tfar)) return 1;   /* no frame for it: may hit */
    if (proxy->root == BRT_EMPTY_ROOT) return 0;
    frame_setup(r, proxy, ray);
    r->any = !t_entry;
    r->lo = tnear;
    r->hi = tfar;
    if (r->levels == 2) {
        *root = dag->leaves[proxy->root];
        *m = leaf_octants(*root);
    } else {
        *root = proxy->root;
        *m = dag->words[proxy->root] & 0xFFu;
    }
    return -1;
}

/* What both casts do last: the best entry, rounded down to float and
** clamped to tnear, when a set voxel was touched. */
static int cast_end(const ray_frame *r, float tnear, float *t_entry)
{
    float t;
    if (!r->found) return 0;
    t = (float)r->hi;
    if ((double)t > r->hi) t = nextafterf(t, -INFINITY);
    if (t_entry) *t_entry = t > tnear ? t : tnear;
    return 1;
}

/* ===================================================================== */
/* The reference cast: Laine and Karras, written for reading               */
/* ===================================================================== */

/*
** The plain traversal of Laine and Karras (2010, section 3 and the castRay
** listing of their technical report) in one function, one phase after
** another with the paper's names:
**   INITIALIZE  the frame (frame_setup: the root cube mapped to [1,2]^3,
**               the ray mirrored so that it runs towards smaller
**               coordinates, octant_mask = r.mirror; tx_coef and tx_bias
**               are r.step and r.enter_bias) and the root's [t_min, t_max]
**               (clip_to_root);
**   PUSH        descend into the current child: it is not empty, and the
**               segment touches it (ADVANCE chose it so);
**   ADVANCE     step to the sibling the ray enters next;
**   POP         when no sibling is left, return to the parent's scale.
** Positions are integers in voxels of the finest level (the numbers ESVO
** keeps in float mantissas), so `pos` is exact; `scale` is the level of the
** parent (its side is 2^scale voxels; ESVO counts the same levels).  A
** child's interval is a plain slab test of its grown box (the box of the
** voxels it spans, grown by g on every side, see CONSERVATIVE IN FLOAT
** above), so the rounding argument holds for every number here.  ESVO's
** h (the stack entry that is still valid) only saves stack writes; here
** the stack is written at every PUSH.
**
** ADVANCE.  ESVO steps from the current child across the face through which
** the ray leaves it: step_mask holds every axis whose exit plane comes
** first.  When two (three) exit planes are crossed at the same t the ray
** leaves through an edge (a corner) and ESVO flips two (three) bits at once,
** stepping diagonally -- and never visits the cubes that share only that
** edge or corner with the current one.  A closed box contains its edges and
** corners, so the ray touches those cubes; and the grown boxes overlap, so
** a ray that passes within g of an edge touches both cubes beside it as
** well.  A proxy must report them all.  So ADVANCE does not step across a
** face: it takes, among all eight children, the non-empty one whose grown
** box the segment enters next -- the least (t_min, idx) after the current
** child's, in lexicographic order so that children entered at the same t
** are each taken once.  Which child comes first among equal t_min does not
** change the answer: it is the least entry over every touched voxel.
** "Touched" is t_min <= t_max, and a child entered at or after the best
** hit so far (r.hi once r.found) can not beat it and is skipped.
**
** Not for speed: every ADVANCE tests all eight siblings.  The fast cast
** below visits the same children in an order of its own; the tests check
** that the two answer alike.
*/
typedef struct lk_scale {
    uint64_t parent;        /* a pool node, a leaf's 64 bits, an octant's 8 */
    unsigned child_mask;    /* the parent's non-empty children (world index) */
    uint32_t pos[3];        /* the parent's mirrored corner, in voxels */
    unsigned idx;           /* the current child (mirrored index; 8: none) */
    double t_min;           /* ... and where the segment enters it */
} lk_scale;

/* The segment's interval in the grown box of the child idx of a parent of
** side 2^scale at mirrored corner pos: bit a of idx says "upper half on
** axis a", which the ray (running to smaller coordinates) meets first. */
static void lk_child_interval(const ray_frame *r, const uint32_t pos[3], int scale,
                              unsigned idx, double *t_min, double *t_max)
{
    uint32_t half = 1u << (scale - 1);
    int a;
    *t_min = r->lo;
    *t_max = r->hi;
    for (a = 0; a < 3; a++) {
        uint32_t low = pos[a] + ((idx >> a) & 1) * half;
        *t_min = max2(*t_min, enter_t(r, a, low + half));
        *t_max = min2(*t_max, leave_t(r, a, low));
    }
}

int brt_proxy_raycast_reference(const brt_svdag *dag, const brt_proxy *proxy,
                                const brt_ray *ray, float tnear, float tfar,
                                float *t_entry)
{
    lk_scale stack[MAX_LEVEL + 1], *s;
    ray_frame r;
    uint64_t root;
    unsigned root_mask, idx, next;
    int scale, popped = 0, a;
    double t_next;
    /* INITIALIZE: the frame and the root's [t_min, t_max]; the root is the
    ** parent of the first scale, with no current child yet (idx 8) */
    int early = cast_begin(dag, proxy, ray, tnear, tfar, t_entry, &r, &root, &root_mask);
    if (early >= 0) return early;
    if (!clip_to_root(&r)) return 0;
    scale = r.levels;
    s = &stack[scale];
    s->parent = root;
    s->child_mask = root_mask;
    s->pos[0] = s->pos[1] = s->pos[2] = 0;
    s->idx = 8;
    s->t_min = -INFINITY;
    for (;;) {
        if (s->idx < 8 && scale == 1) {
            /* the current child is a set voxel: the best hit so far */
            r.hi = s->t_min;
            r.found = 1;
            if (r.any) break;           /* yes/no: nothing more to learn */
        } else if (s->idx < 8 && !popped) {
            /* PUSH: the current child becomes the parent, with no current
            ** child yet (a child just popped from is not entered again) */
            lk_scale *child = &stack[scale - 1];
            uint32_t half = 1u << (scale - 1);
            child->parent = child_fetch(dag, s->parent, scale, s->idx ^ r.mirror,
                                        &child->child_mask);
            for (a = 0; a < 3; a++) child->pos[a] = s->pos[a] + ((s->idx >> a) & 1) * half;
            child->idx = 8;
            child->t_min = -INFINITY;
            scale--;
            s = child;
        }
        /* ADVANCE: the touched non-empty sibling with the least (t_min, idx)
        ** after the current one's (see ADVANCE above) */
        next = 8;
        t_next = INFINITY;
        for (idx = 0; idx < 8; idx++) {
            double t_min, t_max;
            if (!((s->child_mask >> (idx ^ r.mirror)) & 1)) continue;      /* empty */
            lk_child_interval(&r, s->pos, scale, idx, &t_min, &t_max);
            if (t_min > t_max || (r.found && t_min >= r.hi)) continue;    /* missed */
            if (t_min < s->t_min || (t_min == s->t_min && idx <= s->idx)) continue;  /* done */
            if (next == 8 || t_min < t_next) {
                next = idx;
                t_next = t_min;
            }
        }
        s->idx = next;
        s->t_min = t_next;
        /* POP: no sibling left; the parent's current child is finished */
        popped = next == 8;
        if (popped && ++scale > r.levels) break;
        s = &stack[scale];
    }
    return cast_end(&r, tnear, t_entry);
}

/* ===================================================================== */
/* The fast cast                                                           */
/* ===================================================================== */

/*
** WHY NOT ESVO'S ADVANCE STEP.  ESVO steps from a cube to its neighbour
** through the face the ray leaves by, and misses the cubes that the ray
** only touches at an edge or a corner (the reference cast's ADVANCE above
** shows where, in ESVO's own structure).  So PUSH finds, from the node's
** three centre planes, every child whose grown box the segment touches
** (push_node), ADVANCE takes the next of them, POP returns to the parent
** scale.  The two bit-mask levels of a leaf are walked the same way (a
** leaf's octants, an octant's voxels).  A set voxel becomes the best hit;
** from then on a child entered at or behind it is passed over, and the
** walk only finishes the children (siblings of the hit and of its
** ancestors) that the segment enters sooner, because a grown sibling may
** start before the hit.  Before it descends into a node the walk tests the
** box of the node's set voxels (BOUNDS TEST).
**
** COST.  Each of these steps is there to cut the instructions of a
** culled cast, which build/bench_svdag --scene landscape (or island)
** measures under callgrind with --toggle-collect=cast_culled (its header
** says how).  Every step answers bit for bit as the reference cast on the
** tests' rays.
*/

/* One scale of the parent stack: a node, its mirrored corner in voxels,
** its live interval [tin, tout], its three centre planes' entries and
** exits, and the children still to visit, as a set of far-side sets (see
** push_node).  Above the leaves a node is a pool word offset; at level 2
** it is a leaf's 64 bits, and at level 1 the 8 voxels of one 2x2x2 octant
** of a leaf, so the bit-mask levels are walked like any other. */
typedef struct scale_entry {
    uint64_t node;
    uint32_t corner[3];
    double tin, tout;
    double e[3];            /* centre plane of axis a: the far half entered */
    double l[3];            /* ... and the near half left (e + gap) */
    unsigned pending;       /* bit k: child of far-side set k still to visit */
} scale_entry;

/* All children when keep, else those of mask (a select, not a branch). */
static unsigned all_or(int keep, unsigned mask)
{
    return keep ? 0xFFu : mask;
}

/* A world child mask m (bit w: child w is set) by far-side set: bit k of
** the result is bit k ^ x of m, x = 7 ^ mirror (see push_node).  XOR with
** a constant permutes bit indices by swapping bits, pairs and nibbles. */
static unsigned by_far_set(unsigned m, unsigned x)
{
    m = x & 1u ? ((m & 0x55u) << 1) | ((m >> 1) & 0x55u) : m;
    m = x & 2u ? ((m & 0x33u) << 2) | ((m >> 2) & 0x33u) : m;
    return x & 4u ? ((m & 0x0Fu) << 4) | (m >> 4) : m;
}

/* The children whose far-side set has bit a: 0xAA, 0xCC, 0xF0. */
#define FAR0 0xAAu
#define FAR1 0xCCu
#define FAR2 0xF0u

/*
** PUSH: the node spanning 2^level voxels at a mirrored corner, entered on
** [tin, tout], whose set children form the world mask m.  Only the three
** centre planes are new: a child's other faces are its parent's.  Name a
** child by its FAR-SIDE SET k: bit a of k says it lies beyond the centre
** plane of axis a (ESVO's idx is 7 ^ k, the world index 7 ^ k ^ mirror).
** Then its interval is
**     [max(tin, e_a for a in k), min(tout, l_a for a not in k)]
** (a centre plane is crossed after the node's entry plane on that axis,
** so the parent's faces add nothing): the same numbers a slab test of each
** child computes, from 6 plane distances instead of 12.
** LIVE: that interval is not empty when each lower bound is below each
** upper bound: e_a <= tout for a in k, tin <= l_b for b not in k, and
** e_a <= l_b for a in k, b not in k (6 ordered pairs of axes); with k the
** bit index these are masks fixed at compile time, and nothing branches.
** ORDER: the children are visited by increasing k.  A child's entry only
** grows when axes join its far-side set, so k comes after every subset of
** itself; child 0 (entered at tin) is first, child 7 last.  It is not
** ESVO's ray order: the entries are not sorted, because a sorted order
** pays off only when a hit ends its scale, and the render's casts are
** yes/no casts that stop at the first set voxel anyway.  So each child is
** compared with the best hit instead.
*/
static void push_node(const ray_frame *r, scale_entry *s, uint64_t node,
                      unsigned m, const uint32_t corner[3], int level,
                      double tin, double tout)
{
    uint32_t half = 1u << (level - 1);
    double e0 = enter_t(r, 0, corner[0] + half), e1 = enter_t(r, 1, corner[1] + half);
    double e2 = enter_t(r, 2, corner[2] + half);
    double l0 = e0 + r->gap[0], l1 = e1 + r->gap[1], l2 = e2 + r->gap[2];
    unsigned live;
    s->node = node;
    s->tin = tin;
    s->tout = tout;
    s->corner[0] = corner[0];
    s->corner[1] = corner[1];
    s->corner[2] = corner[2];
    s->e[0] = e0;
    s->e[1] = e1;
    s->e[2] = e2;
    s->l[0] = l0;
    s->l[1] = l1;
    s->l[2] = l2;
    /* LIVE: far side reached in time, near side not left before tin, no
    ** far side entered after a near side is left */
    live = all_or(e0 <= tout, ~FAR0) & all_or(e1 <= tout, ~FAR1) & all_or(e2 <= tout, ~FAR2) &
           all_or(l0 >= tin, FAR0) & all_or(l1 >= tin, FAR1) & all_or(l2 >= tin, FAR2) &
           all_or(e1 <= l0, ~(FAR1 & ~FAR0)) & all_or(e2 <= l0, ~(FAR2 & ~FAR0)) &
           all_or(e0 <= l1, ~(FAR0 & ~FAR1)) & all_or(e2 <= l1, ~(FAR2 & ~FAR1)) &
           all_or(e0 <= l2, ~(FAR0 & ~FAR2)) & all_or(e1 <= l2, ~(FAR1 & ~FAR2));
    s->pending = live & by_far_set(m, 7u ^ r->mirror);
}

/* Subtracted from a centre entry: nothing when the child is beyond that
** plane, else everything (the entry then does not bound the child). */
static const double near_off[2] = {INFINITY, 0};
/* Added to a centre exit: nothing when the child is before that plane. */
static const double far_off[2] = {0, INFINITY};

/*
** BOUNDS TEST: the box of a node's set voxels (its header's bounds, in
** eighths of its side; layout at the top), turned into the mirrored frame
** (a mirrored axis swaps first and last: eighth i becomes 7 - i), clamps
** the node's interval [*tin, *tout]; 0 when the segment misses the box.
** ROUNDING.  The box's planes are voxel planes and go through enter_t and
** leave_t like every other plane, grown by g.  A computed plane distance,
** bias - u * step with step > 0, never increases with u (each rounding is
** monotone), so for every set voxel v inside the box the computed entry
** of v on each axis is at least the box's and its exit at most the box's:
** v's computed interval lies inside the box's.  So a node whose box is
** missed holds no touched voxel, and max/min with the box's planes leave
** every voxel's computed entry and exit as they were: the cast answers
** bit for bit as without the test (and as the reference cast).
*/

static WALK_INLINE int clip_to_bounds(const ray_frame *r, uint32_t header, const uint32_t corner[3],
                          int level, double *tin, double *tout)
{
    /* mirrored axes: flip every eighth (i -> 7 - i, an XOR with 7) and
    ** swap first and last, all three fields at once */
    uint32_t f = (header >> BOUNDS_SHIFT) ^ r->bounds_flip, swap = r->bounds_flip;
    int shift = level - 3;          /* an eighth spans 2^(level-3) voxels */
    double in, out;
    f = (f & ~swap) | ((f >> 3) & swap & 0x71C7u) | ((f << 3) & swap & 0x38E38u);
    in = max2(max2(*tin, enter_t(r, 0, corner[0] + ((((f >> 3) & 7u) + 1) << shift))),
              max2(enter_t(r, 1, corner[1] + ((((f >> 9) & 7u) + 1) << shift)),
                   enter_t(r, 2, corner[2] + ((((f >> 15) & 7u) + 1) << shift))));
    out = min2(min2(*tout, leave_t(r, 0, corner[0] + ((f & 7u) << shift))),
               min2(leave_t(r, 1, corner[1] + (((f >> 6) & 7u) << shift)),
                    leave_t(r, 2, corner[2] + (((f >> 12) & 7u) << shift))));
    *tin = in;
    *tout = out;
    return in <= out;
}

/* The walk from the root; returns 0 when it hit the iteration cap.  Each
** child is entered at in = max(tin, e_a for a in k); a set voxel lowers hi
** to its entry, and from then on a child entered at or after hi is passed
** over (it holds nothing nearer). */
static int walk(const brt_svdag *dag, ray_frame *r, uint64_t node, unsigned m)
{
    scale_entry stack[MAX_LEVEL + 1], *s;
    uint32_t corner[3] = {0, 0, 0};
    double tin, tout;
    long budget = 64L * (1L << r->levels) + 4096;
    int level = r->levels;
    /* the segment in the root's box of set voxels, or in the root cube when
    ** the root is a leaf (see BOUNDS TEST: the same answers either way) */
    if (level > 2 ? !clip_to_bounds(r, dag->words[node], corner, level, &r->lo, &r->hi)
                  : !clip_to_root(r))
        return 1;
    tin = r->lo;
    tout = r->hi;
    for (;;) {
        s = &stack[level];
        push_node(r, s, node, m, corner, level, tin, tout);      /* PUSH */
        for (;;) {
            uint32_t half = 1u << (level - 1);
            unsigned k, j;
            double in;
            if (!s->pending) {                                     /* POP */
                if (++level > r->levels) return 1;
                s = &stack[level];
                continue;
            }
            k = lowest_bit64(s->pending);                      /* ADVANCE */
            s->pending &= s->pending - 1;
            in = max2(max2(s->tin, s->e[0] - near_off[k & 1]),
                      max2(s->e[1] - near_off[(k >> 1) & 1], s->e[2] - near_off[k >> 2]));
            if (in > r->hi || (in == r->hi && r->found)) continue;  /* no better */
            if (--budget < 0) return 0;
            if (level == 1) {                   /* a set voxel: the best so far */
                r->hi = in;
                r->found = 1;
                if (r->any) return 1;   /* yes/no: nothing more to learn */
                continue;
            }
            tout = min2(min2(s->tout, r->hi),
                        min2(s->l[0] + far_off[k & 1],
                             min2(s->l[1] + far_off[(k >> 1) & 1], s->l[2] + far_off[k >> 2])));
            j = 7u ^ k;                 /* ESVO's idx: bit a, the upper half */
            corner[0] = s->corner[0] + (j & 1) * half;
            corner[1] = s->corner[1] + ((j >> 1) & 1) * half;
            corner[2] = s->corner[2] + (j >> 2) * half;
            node = child_fetch(dag, s->node, level, j ^ r->mirror, &m);
            tin = in;
            if (level > 3 && !clip_to_bounds(r, dag->words[node], corner, level - 1, &tin, &tout))
                continue;       /* the segment misses the child's set voxels */
            level--;
            break;
        }
    }
}

int brt_proxy_raycast(const brt_svdag *dag, const brt_proxy *proxy,
                      const brt_ray *ray, float tnear, float tfar,
                      float *t_entry)
{
    ray_frame r;
    uint64_t root;
    unsigned m;
    int early = cast_begin(dag, proxy, ray, tnear, tfar, t_entry, &r, &root, &m);
    if (early >= 0) return early;
    if (!walk(dag, &r, root, m)) return 1;      /* gave up: may hit, at tnear */
    return cast_end(&r, tnear, t_entry);
}

/* ===================================================================== */
/* Beyond the paper: inner proxies (its section 4.3)                       */
/* ===================================================================== */
/*
** Voxels that prove an occlusion ray occluded.  The paper names them as
** future work (section 4.3): a second voxelization whose set
** voxels lie certainly inside solid geometry, so that an occlusion ray
** with tfar = +inf that passes through one is occluded without a load.
** The inner grid of a batching point is fitted to its box like the outer
** proxy's and stored as a second root in the same shared pool.
**
** WHICH GEOMETRY QUALIFIES (brt_solids_build).  The triangles of a set --
** the scene build passes a whole bucket, all the triangles it holds in
** memory at once, so a solid cut by batching-point boundaries still counts
** -- are joined into components by exactly equal vertex positions (-0 =
** +0).  A component is CLOSED when every edge (pair of distinct positions)
** is used by an even number of its triangles and none of its triangles is
** degenerate (two equal positions, or a cross product below 2^-40 of
** |e1||e2|).  A closed component is a 2-cycle mod 2, so for points off its
** surface the parity of the number of crossings of any path to infinity is
** well defined (Jordan-Brouwer, mod 2); odd parity is INSIDE.  A component
** that a bucket boundary cuts has edges used once within the set and gets
** nothing (conservative).  Open geometry never counts, neither as a wall
** nor as a solid.
**
** HOW INSIDE IS DECIDED (brt_voxelize_inner).  Every closed triangle of the
** set that comes near the grid's box is voxelized with the conservative
** voxelizer above: an unmarked voxel's closed box touches no closed
** triangle, so a 6-connected set of unmarked voxels is a connected set off
** the surface and has one parity.  A flood fill from the grid's border is
** NOT a proof (a solid may run past the border; a pocket walled in by
** marked voxels of several small solids may be outside, a path leaving it
** through the marked voxels between them), so each component's parity is
** counted: a ray straight up (+y) from one voxel centre against the closed
** triangles whose xz boxes hold the centre (a uniform xz grid over the
** set), in double precision; a triangle too close to call (an xz edge
** function within its rounding bound of 0, parity_up) makes that voxel
** undecided, and up to four voxels of the component are tried before it
** is left out (so is a component past INNER_MAX_COMPONENTS).  Odd count:
** every voxel of the component is inner.  (Nested shells: the space
** between them counts one crossing and is inner; the core inside the inner
** shell counts two and is left out, although a ray from it is occluded
** too: parity is a sufficient test, not a necessary one.  Overlapping
** solids: their common part counts two, left out alike.)
**
** THE MARGIN AND ROUNDING (brt_inner_occludes).  The cast never trusts a
** voxel whole: it takes the voxel's CORE, the box shrunk by a quarter
** voxel on every side, picks t_s in [max(entry, tnear), exit] of the core
** and checks the point there lies in the core (in double, grid units; the
** error there is below 1e-9 voxels under the magnitude condition below).
** The real point P = o + t_s d then lies at least ~cell/4 from every
** closed triangle and is inside, so the ray beyond P crosses the closed
** surface at some t > t_s >= tnear, at least cell/(4|d|) later.  The
** watertight test (Woop, Benthin, Wald 2013) cannot let the ray through
** that surface: vertices are transformed once each, edge functions of a
** shared edge are exact negations of each other, so the closed component
** stays closed for the test and its coverage of the ray's line has the
** parity of the real one (their section 3); the computed t is off by a few
** float ulps of the coordinates' magnitude M.  The cast refuses any ray or
** grid with M >= 2^14 cells (origin, ray origin, far grid corner), so
** those ulps (2^-24 M <= 2^-10 cell) stay far below the cell/4 margin.
** Assumption stated rather than proved: a hit that grazes a long triangle
** can err by more than ulps of M in t; the dense tests (tests/test_inner.c)
** hold the result to the exact query ray by ray.
**
** RAYS FROM INSIDE A SOLID.  Nothing changes: an occlusion ray whose origin
** lies inside a solid and whose tnear is small is occluded by the exact
** query as well (it leaves the solid); with tnear > 0 only core points at
** t_s >= tnear are used, so the hit beyond is at t > tnear too.
**
** STORAGE: a second root per batching point in the shared pool,
** deduplicated with the outer proxies, at half their resolution
** (batchrt.c, inner_res): interiors are mostly solid blocks, which dedup
** to few nodes, but their surfaces are as unique as the outer proxies',
** so at full resolution their surface nodes would add about as many
** unique nodes as the outer proxies hold (make bench-inner prints the
** pool's bytes, proxy_bytes, beside the occlusion rays they stop).
*/

#define INNER_MAX_COMPONENTS 1024u  /* parity decisions per grid */
#define INNER_MAX_CELLS 16384.0     /* 2^14: magnitude bound, in cells */
#define INNER_CORE 0.25             /* the margin: a voxel's core starts here */

struct brt_solids {
    const float *corners;       /* the caller's triangles (kept alive by it) */
    size_t stride;
    uint32_t *ids;              /* the closed ones among them */
    uint32_t count;
    double x0, z0, cx, cz;      /* the xz index: origin and cell sides */
    uint32_t nx, nz;
    uint32_t *first;            /* cell c's triangles: items[first[c] .. first[c+1]) */
    uint32_t *items;
};

/* A corner's position with -0 made +0 (equal values weld), as bits. */
static void corner_bits(const float *v, uint32_t bits[3])
{
    int i;
    for (i = 0; i < 3; i++) {
        float f = v[i] == 0.0f ? 0.0f : v[i];
        memcpy(&bits[i], &f, 4);
    }
}

static const float *corner_at(const float *corners, size_t stride, uint32_t t, int k)
{
    return corners + stride * t + 3 * k;
}

static const float *corner_ref(const float *corners, size_t stride, uint32_t ref)
{
    return corner_at(corners, stride, ref / 3, (int)(ref % 3));
}

/* Corner c's position hash; its bits in b. */
static size_t corner_hash(const float *corners, size_t stride, uint32_t c, uint32_t b[3])
{
    corner_bits(corner_ref(corners, stride, c), b);
    return (size_t)brt_mix64(((uint64_t)b[0] << 32 | b[1]) ^ brt_mix64(b[2]));
}

/* The weld's table at twice its capacity (NULL when out of memory). */
static uint32_t *weld_grow(const float *corners, size_t stride, uint32_t *slot, size_t *cap)
{
    size_t bigger = 2 * *cap, i, h;
    uint32_t *to = calloc(bigger, sizeof *to), b[3];
    for (i = 0; to && i < *cap; i++) {
        if (!slot[i]) continue;
        h = corner_hash(corners, stride, slot[i] - 1, b) & (bigger - 1);
        while (to[h]) h = (h + 1) & (bigger - 1);
        to[h] = slot[i];
    }
    free(slot);
    *cap = bigger;
    return to;
}

/*
** Vertex ids by exact position: vid[3t + k] for corner k of triangle t,
** numbered in the order of their first corners.  An open-addressing table
** (load at most 3/4) holds each position's first corner + 1; a corner
** first takes the first corner of its position as vid, and one pass in
** corner order then compacts: a corner that is its own first gets the next
** id, any other (an earlier corner) the id already given to that one.  The
** table starts at a third of the corners (a closed mesh has about half as
** many vertices as triangles) and doubles when full: 4 bytes a corner and
** about 8 a vertex, where a sort would take twice the corners' positions
** (glibc's qsort copies its array).
*/
static brt_result weld(const float *corners, size_t stride, uint32_t n, uint32_t *vid,
                       uint32_t *unique)
{
    size_t count = 3 * (size_t)n, cap = 64, used = 0, c;
    uint32_t *slot;
    while (cap < count / 3) cap *= 2;
    slot = calloc(cap, sizeof *slot);
    *unique = 0;
    for (c = 0; slot && c < count; c++) {
        uint32_t b[3], o[3];
        size_t h = corner_hash(corners, stride, (uint32_t)c, b) & (cap - 1);
        for (;; h = (h + 1) & (cap - 1)) {
            if (!slot[h]) {
                slot[h] = (uint32_t)c + 1;
                break;
            }
            corner_bits(corner_ref(corners, stride, slot[h] - 1), o);
            if (memcmp(b, o, sizeof b) == 0) break;
        }
        vid[c] = slot[h] - 1;
        if (vid[c] == c && ++used > cap / 4 * 3) slot = weld_grow(corners, stride, slot, &cap);
    }
    free(slot);
    if (c < count) return BRT_ENOMEM;   /* a table that failed to grow */
    for (c = 0; c < count; c++) vid[c] = vid[c] == c ? (*unique)++ : vid[vid[c]];
    return BRT_OK;
}

static uint32_t uf_find(uint32_t *parent, uint32_t v)
{
    while (parent[v] != v) v = parent[v] = parent[parent[v]];
    return v;
}

static int triangle_degenerate(const float *tri, const uint32_t *vid)
{
    double e1[3], e2[3], x[3], l1 = 0, l2 = 0, lx = 0;
    int i;
    if (vid[0] == vid[1] || vid[1] == vid[2] || vid[0] == vid[2]) return 1;
    for (i = 0; i < 3; i++) {
        e1[i] = (double)tri[3 + i] - tri[i];
        e2[i] = (double)tri[6 + i] - tri[i];
    }
    for (i = 0; i < 3; i++) {
        x[i] = e1[(i + 1) % 3] * e2[(i + 2) % 3] - e1[(i + 2) % 3] * e2[(i + 1) % 3];
        l1 += e1[i] * e1[i];
        l2 += e2[i] * e2[i];
        lx += x[i] * x[i];
    }
    return lx <= 0x1p-80 * l1 * l2;
}

#define EDGE_PASSES 4u   /* the edges are listed about a quarter at a time */

/* Corner c's edge (to the next corner of its triangle): lower end, upper end. */
static void corner_edge(const uint32_t *vid, size_t c, uint32_t *lo, uint32_t *hi)
{
    uint32_t u = vid[c], v = vid[c % 3 == 2 ? c - 2 : c + 1];
    *lo = u < v ? u : v;
    *hi = u < v ? v : u;
}

/* The edges of the set listed by lower end a, every use once: their
** places, start[a] .. start[a + 1] (start: unique + 1 entries, zeroed). */
static void edge_offsets(const uint32_t *vid, uint32_t n, uint32_t unique, uint32_t *start)
{
    size_t c;
    uint32_t a, b;
    for (c = 0; c < 3 * (size_t)n; c++) {
        corner_edge(vid, c, &a, &b);
        start[a + 1]++;
    }
    for (a = 0; a < unique; a++) start[a + 1] += start[a];
}

/* The end of a pass's range of lower ends from lo: at most chunk edges,
** or one vertex's edges when they are more. */
static uint32_t edge_range(const uint32_t *start, uint32_t unique, uint32_t lo, size_t chunk)
{
    uint32_t hi = lo + 1;
    while (hi < unique && start[hi + 1] - start[lo] <= chunk) hi++;
    return hi;
}

/* The upper ends of the edges with lower ends lo .. hi - 1, at
** adj[start[a] - start[lo] ..]: one scan of the corners per pass, so that
** adj holds a pass's edges (4 bytes each), not all of them. */
static void edge_lists(const uint32_t *vid, uint32_t n, uint32_t lo, uint32_t hi, uint32_t *start,
                       uint32_t *adj)
{
    uint32_t base = start[lo], a, b;
    size_t c;
    for (c = 0; c < 3 * (size_t)n; c++) {   /* moves start[a] to the end of a's list ... */
        corner_edge(vid, c, &a, &b);
        if (a >= lo && a < hi) adj[start[a]++ - base] = b;
    }
    for (a = hi - 1; a > lo; a--) start[a] = start[a - 1];
    start[lo] = base;                       /* ... so shift back by one vertex */
}

/* bad[root] = 1 for the components with an edge of lower end lo .. hi - 1
** used an odd number of times: a's list toggles odd[b] per use, a second
** walk reads and clears it (linear; odd is zero before and after). */
static void odd_edges(const uint32_t *start, const uint32_t *adj, uint32_t lo, uint32_t hi,
                      uint32_t *parent, unsigned char *odd, unsigned char *bad)
{
    uint32_t a, e, base = start[lo];
    for (a = lo; a < hi; a++) {
        for (e = start[a] - base; e < start[a + 1] - base; e++) odd[adj[e]] ^= 1;
        for (e = start[a] - base; e < start[a + 1] - base; e++) {
            if (odd[adj[e]]) bad[uf_find(parent, a)] = 1;
            odd[adj[e]] = 0;
        }
    }
}

/* The edges of odd use (odd_edges), listed EDGE_PASSES ranges at a time. */
static brt_result odd_edges_all(const uint32_t *vid, uint32_t n, uint32_t unique,
                                uint32_t *parent, unsigned char *bad)
{
    size_t chunk = 3 * (size_t)n / EDGE_PASSES + 1, most = 0;
    uint32_t *start = calloc((size_t)unique + 1, sizeof *start), *adj = NULL, lo, hi;
    unsigned char *odd = calloc((size_t)unique + 1, 1);
    brt_result r;
    if (start) edge_offsets(vid, n, unique, start);
    for (lo = 0; start && lo < unique; lo = hi) {
        hi = edge_range(start, unique, lo, chunk);
        most = most > start[hi] - start[lo] ? most : start[hi] - start[lo];
    }
    if (start && odd) adj = malloc((most + 1) * sizeof *adj);
    for (lo = 0; adj && lo < unique; lo = hi) {
        hi = edge_range(start, unique, lo, chunk);
        edge_lists(vid, n, lo, hi, start, adj);
        odd_edges(start, adj, lo, hi, parent, odd, bad);
    }
    r = adj ? BRT_OK : BRT_ENOMEM;
    free(start);
    free(odd);
    free(adj);
    return r;
}

/* closed[t] = 1 for the triangles of closed components (header above). */
static brt_result closed_triangles(const float *corners, size_t stride, uint32_t n,
                                   unsigned char *closed)
{
    uint32_t *vid = malloc((3 * (size_t)n + 1) * sizeof *vid), unique = 0, *parent = NULL, t;
    unsigned char *bad = NULL;
    /* weld's table is freed before the edges are listed: the peak is 5
    ** bytes a corner and 10 a vertex, 15 T + 10 V bytes for T triangles
    ** with V distinct positions (V is about T / 2 on a closed mesh) */
    brt_result r = vid ? weld(corners, stride, n, vid, &unique) : BRT_ENOMEM;
    if (r == BRT_OK) {
        parent = malloc(((size_t)unique + 1) * sizeof *parent);
        bad = calloc((size_t)unique + 1, 1);
        if (!parent || !bad) r = BRT_ENOMEM;
    }
    if (r != BRT_OK) goto done;
    for (t = 0; t < unique; t++) parent[t] = t;
    for (t = 0; t < n; t++) {
        const uint32_t *v = vid + 3 * (size_t)t;
        parent[uf_find(parent, v[1])] = uf_find(parent, v[0]);
        parent[uf_find(parent, v[2])] = uf_find(parent, v[0]);
    }
    for (t = 0; t < n; t++)
        if (triangle_degenerate(corner_at(corners, stride, t, 0), vid + 3 * (size_t)t))
            bad[uf_find(parent, vid[3 * (size_t)t])] = 1;
    r = odd_edges_all(vid, n, unique, parent, bad);
    if (r != BRT_OK) goto done;
    for (t = 0; t < n; t++) closed[t] = !bad[uf_find(parent, vid[3 * (size_t)t])];
done:
    free(vid);
    free(parent);
    free(bad);
    return r;
}

/* ---- the xz index of the closed triangles ---- */

/* Closed triangle t's 9 floats. */
static const float *solid_tri(const brt_solids *s, uint32_t t)
{
    return corner_at(s->corners, s->stride, s->ids[t], 0);
}

static void cell_range(const brt_solids *s, double lo, double hi, int z, uint32_t *a, uint32_t *b)
{
    double o = z ? s->z0 : s->x0, c = z ? s->cz : s->cx, n = z ? s->nz : s->nx;
    double fa = floor((lo - o) / c), fb = floor((hi - o) / c);
    *a = fa < 0 ? 0 : fa >= n ? (uint32_t)n - 1 : (uint32_t)fa;
    *b = fb < 0 ? 0 : fb >= n ? (uint32_t)n - 1 : (uint32_t)fb;
}

static void tri_extent(const float *t, int axis, double *lo, double *hi)
{
    *lo = min2(t[axis], min2(t[3 + axis], t[6 + axis]));
    *hi = max2(t[axis], max2(t[3 + axis], t[6 + axis]));
}

/* Counting pass (items NULL: first[] counts) or filling pass. */
static void index_pass(brt_solids *s, uint32_t *items)
{
    uint32_t t, x, z, a[2], b[2];
    for (t = 0; t < s->count; t++) {
        double lo, hi;
        tri_extent(solid_tri(s, t), 0, &lo, &hi);
        cell_range(s, lo, hi, 0, &a[0], &b[0]);
        tri_extent(solid_tri(s, t), 2, &lo, &hi);
        cell_range(s, lo, hi, 1, &a[1], &b[1]);
        for (z = a[1]; z <= b[1]; z++)
            for (x = a[0]; x <= b[0]; x++) {
                uint32_t c = x + s->nx * z;
                if (items) items[s->first[c]++] = t;
                else s->first[c + 1]++;
            }
    }
}

static brt_result build_index(brt_solids *s)
{
    double xlo = INFINITY, xhi = -INFINITY, zlo = INFINITY, zhi = -INFINITY, lo, hi;
    uint32_t t, c, side = 1, cells;
    while (side < 1024 && (uint64_t)side * side * 4 < s->count) side *= 2;
    for (t = 0; t < s->count; t++) {
        tri_extent(solid_tri(s, t), 0, &lo, &hi);
        xlo = min2(xlo, lo); xhi = max2(xhi, hi);
        tri_extent(solid_tri(s, t), 2, &lo, &hi);
        zlo = min2(zlo, lo); zhi = max2(zhi, hi);
    }
    s->nx = s->nz = side;
    s->x0 = s->count ? xlo : 0;
    s->z0 = s->count ? zlo : 0;
    s->cx = s->count && xhi > xlo ? (xhi - xlo) / side * (1 + 0x1p-40) : 1;
    s->cz = s->count && zhi > zlo ? (zhi - zlo) / side * (1 + 0x1p-40) : 1;
    cells = side * side;
    s->first = calloc((size_t)cells + 1, sizeof *s->first);
    if (!s->first) return BRT_ENOMEM;
    index_pass(s, NULL);
    for (c = 0; c < cells; c++) s->first[c + 1] += s->first[c];
    s->items = malloc(((size_t)s->first[cells] + 1) * sizeof *s->items);
    if (!s->items) return BRT_ENOMEM;
    index_pass(s, s->items);   /* moves first[c] to the end of cell c ... */
    for (c = cells; c > 0; c--) s->first[c] = s->first[c - 1];
    s->first[0] = 0;           /* ... so shift back by one cell */
    return BRT_OK;
}

brt_result brt_solids_build(const float *corners, size_t stride, uint32_t tri_count,
                            brt_solids **out)
{
    brt_solids *s = calloc(1, sizeof *s);
    unsigned char *closed = malloc((size_t)tri_count + 1);
    brt_result r = s && closed ? closed_triangles(corners, stride, tri_count, closed) : BRT_ENOMEM;
    uint32_t t;
    *out = NULL;
    if (r == BRT_OK) {
        for (t = 0; t < tri_count; t++) s->count += closed[t];
        s->ids = malloc(((size_t)s->count + 1) * sizeof *s->ids);
        s->corners = corners;
        s->stride = stride;
        if (!s->ids) r = BRT_ENOMEM;
    }
    if (r == BRT_OK) {
        uint32_t m = 0;
        for (t = 0; t < tri_count; t++)
            if (closed[t]) s->ids[m++] = t;
        r = build_index(s);
    }
    free(closed);
    if (r == BRT_OK) *out = s;
    else brt_solids_free(s);
    return r;
}

uint32_t brt_solids_triangles(const brt_solids *s)
{
    return s ? s->count : 0;
}

void brt_solids_free(brt_solids *s)
{
    if (!s) return;
    free(s->ids);
    free(s->first);
    free(s->items);
    free(s);
}

/* ---- parity ---- */

/* The xz edge function of a -> b at p, and its rounding bound: each
** difference and product rounds once (relative 2^-53), so the error is
** below 2^-50 times the sum of the products' magnitudes. */
static double edge_xz(const float *a, const float *b, const double p[3], double *bound)
{
    double l = ((double)b[0] - a[0]) * (p[2] - a[2]), r = ((double)b[2] - a[2]) * (p[0] - a[0]);
    *bound = 0x1p-50 * (fabs(l) + fabs(r));
    return l - r;
}

/*
** Parity of the crossings of the ray c + t (0, 1, 0), t > 0, with the
** closed triangles: 1 odd, 0 even, -1 when a triangle is too close to
** call.  A triangle is crossed when c's xz point is strictly inside its xz
** projection (three edge functions of one sign, each beyond its bound:
** then the exact ones have that sign too) and the triangle's height there
** is above c.  c lies at least half a cell from every closed triangle
** (walls), so the height is never near c's; one within a quarter cell is
** called undecided all the same.
*/
static int parity_up(const brt_solids *s, const double c[3], double cell)
{
    uint32_t x, z, k, cellno;
    int odd = 0;
    cell_range(s, c[0], c[0], 0, &x, &k);
    cell_range(s, c[2], c[2], 1, &z, &k);
    cellno = x + s->nx * z;
    for (k = s->first[cellno]; k < s->first[cellno + 1]; k++) {
        const float *t = solid_tri(s, s->items[k]);
        double w[3], bound[3], y;
        int i, pos = 0, neg = 0, near = 0;
        for (i = 0; i < 3; i++) {
            w[i] = edge_xz(t + 3 * ((i + 1) % 3), t + 3 * ((i + 2) % 3), c, &bound[i]);
            pos |= w[i] > bound[i];
            neg |= w[i] < -bound[i];
            near |= fabs(w[i]) <= bound[i];
        }
        if (pos && neg) continue;      /* clearly outside */
        if (near) return -1;
        y = (w[0] * t[1] + w[1] * t[4] + w[2] * t[7]) / (w[0] + w[1] + w[2]);
        if (fabs(y - c[1]) < 0.25 * cell) return -1;
        odd ^= y > c[1];
    }
    return odd;
}

/* The parity of a component (voxels queue[0..count)): the first of up to
** four of its voxels that decides; 0 when none does. */
static int component_inside(const brt_grid *g, const brt_solids *s, const uint32_t *queue,
                            uint32_t count)
{
    uint32_t k, res = g->res;
    for (k = 0; k < 4; k++) {
        uint32_t i = queue[(uint64_t)count * k / 4], at[3], a;
        double c[3];
        int odd;
        at[0] = i % res; at[1] = i / res % res; at[2] = i / res / res;
        for (a = 0; a < 3; a++) c[a] = g->origin[a] + ((double)at[a] + 0.5) * g->cell;
        odd = parity_up(s, c, g->cell);
        if (odd >= 0) return odd;
    }
    return 0;
}

/* Voxel j of a grid (index x + res (y + res z), as voxel_index), in its
** words: read, or set. */
static int voxel_bit(const uint64_t *bits, uint32_t j)
{
    return (int)((bits[j >> 6] >> (j & 63)) & 1);
}

static void voxel_mark(uint64_t *bits, uint32_t j)
{
    bits[j >> 6] |= 1ull << (j & 63);
}

/* Voxel j into the flood's queue unless seen (a wall, or queued before). */
static uint32_t flood_visit(uint64_t *seen, uint32_t *queue, uint32_t count, uint32_t j)
{
    if (voxel_bit(seen, j)) return count;
    voxel_mark(seen, j);
    queue[count] = j;
    return count + 1;
}

/* The 6-connected voxels not seen from queue[0..count), marked seen; res
** = 2^shift.  Neighbours in the order -x, +x, -y, +y, -z, +z (the queue's
** order picks the voxels component_inside tries). */
static uint32_t flood(uint64_t *seen, uint32_t shift, uint32_t *queue, uint32_t count)
{
    uint32_t res = 1u << shift, head, a;
    for (head = 0; head < count; head++) {
        uint32_t i = queue[head];
        for (a = 0; a < 3; a++) {
            uint32_t at = (i >> (shift * a)) & (res - 1), step = 1u << (shift * a);
            if (at > 0) count = flood_visit(seen, queue, count, i - step);
            if (at + 1 < res) count = flood_visit(seen, queue, count, i + step);
        }
    }
    return count;
}

/* Each component of the voxels not seen (seen: the walls' bits, which it
** fills), set in inner when its parity is odd. */
static void inner_components(const brt_grid *walls, brt_grid *inner, const brt_solids *s,
                             uint64_t *seen, uint32_t *queue)
{
    uint32_t res = walls->res, voxels = res * res * res, j, count, components = 0, k;
    uint32_t shift = (uint32_t)resolution_log2(res);
    for (j = 0; j < voxels; j++) {
        if ((j & 63) == 0 && seen[j >> 6] == ~(uint64_t)0) j += 63;   /* a word all seen */
        else if (!voxel_bit(seen, j)) {
            voxel_mark(seen, j);
            queue[0] = j;
            count = flood(seen, shift, queue, 1);
            if (++components > INNER_MAX_COMPONENTS || !component_inside(walls, s, queue, count))
                continue;
            for (k = 0; k < count; k++) voxel_mark(inner->bits, queue[k]);
        }
    }
}

/* The walls: every closed triangle whose box comes within a cell of the
** grid's box (the others cannot touch a voxel), voxelized once each. */
static brt_result voxelize_walls(brt_grid *walls, const brt_solids *s)
{
    double lo[3], hi[3];
    uint32_t a[2], b[2], x, z, k;
    unsigned char *done = calloc((size_t)s->count + 1, 1);
    int i;
    if (!done) return BRT_ENOMEM;
    for (i = 0; i < 3; i++) {
        lo[i] = walls->origin[i] - (double)walls->cell;
        hi[i] = walls->origin[i] + ((double)walls->res + 1) * walls->cell;
    }
    cell_range(s, lo[0], hi[0], 0, &a[0], &b[0]);
    cell_range(s, lo[2], hi[2], 1, &a[1], &b[1]);
    for (z = a[1]; z <= b[1]; z++)
        for (x = a[0]; x <= b[0]; x++)
            for (k = s->first[x + s->nx * z]; k < s->first[x + s->nx * z + 1]; k++) {
                uint32_t t = s->items[k];
                const float *v = solid_tri(s, t);
                double q[3][3], tlo, thi;
                int c, near = 1;
                if (done[t]) continue;
                done[t] = 1;
                for (i = 0; i < 3; i++) {
                    tri_extent(v, i, &tlo, &thi);
                    near &= thi >= lo[i] && tlo <= hi[i];
                }
                if (!near) continue;
                for (c = 0; c < 3; c++)
                    for (i = 0; i < 3; i++)
                        q[c][i] = ((double)v[3 * c + i] - walls->origin[i]) / walls->cell;
                voxelize_triangle(walls, q, 0.0);
            }
    free(done);
    return BRT_OK;
}

brt_result brt_voxelize_inner(brt_grid *inner, const brt_solids *solids)
{
    uint32_t *queue;
    brt_grid walls;
    brt_result r;
    if (!grid_frame_valid(inner) || !solids) return BRT_EARG;
    if (solids->count == 0) return BRT_OK;
    queue = malloc((size_t)inner->res * inner->res * inner->res * sizeof *queue);
    r = queue ? grid_alloc(&walls, inner->res, inner->origin, inner->cell) : BRT_ENOMEM;
    if (r == BRT_OK) {
        r = voxelize_walls(&walls, solids);
        /* the walls' bits become the flood's "seen" marks */
        if (r == BRT_OK) inner_components(&walls, inner, solids, walls.bits, queue);
        free(walls.bits);
    }
    free(queue);
    return r;
}

/* ---- the cast ---- */

/* Size of the empty node around voxel at[] (log2 of its side), or -1 when
** the voxel is set. */
static int inner_lookup(const brt_svdag *dag, uint32_t root, int levels, const uint32_t at[3])
{
    uint32_t id = root;
    int level;
    for (level = levels; level > 2; level--) {
        uint32_t header = dag->words[id], b = level - 1;
        unsigned c = ((at[0] >> b) & 1) | ((at[1] >> b) & 1) << 1 | ((at[2] >> b) & 1) << 2;
        if (!(header & (1u << c))) return (int)b;
        id = dag->words[id + 1 + popcount8(header & ((1u << c) - 1))];
    }
    return (dag->leaves[id] >> ((at[0] & 3) + 4 * ((at[1] & 3) + 4 * (at[2] & 3)))) & 1 ? -1 : 0;
}

/* The ray's parameter interval through [lo, hi] on one axis (grid units). */
static void slab(double g, double gd, double lo, double hi, double *t0, double *t1)
{
    if (gd == 0) {
        if (!(g > lo && g < hi)) *t1 = -INFINITY;
        return;
    }
    *t0 = max2(*t0, ((gd > 0 ? lo : hi) - g) / gd);
    *t1 = min2(*t1, ((gd > 0 ? hi : lo) - g) / gd);
}

/* The margin check of the header: a point of the ray at t >= tnear that
** lies in the voxel's core (the box shrunk by a quarter voxel). */
static int core_holds(const double g[3], const double gd[3], const uint32_t at[3], double tnear)
{
    double t0 = tnear, t1 = INFINITY, ts;
    int a;
    for (a = 0; a < 3; a++) slab(g[a], gd[a], at[a] + INNER_CORE, at[a] + 1 - INNER_CORE, &t0, &t1);
    if (!(t0 < t1)) return 0;
    ts = 0.5 * (t0 + t1);
    for (a = 0; a < 3; a++) {
        double q = g[a] + ts * gd[a];
        if (!(q > at[a] + INNER_CORE && q < at[a] + 1 - INNER_CORE)) return 0;
    }
    return ts >= tnear;
}

/* The ray in grid units; 0 when the cast must refuse it (header). */
static int inner_frame(const brt_proxy *p, const brt_ray *ray, double g[3], double gd[3])
{
    double limit = INNER_MAX_CELLS * p->cell, moving = 0;
    int a;
    if (!(ray->tfar == INFINITY) || !isfinite(ray->tnear) || !brt_ray_valid(ray)) return 0;
    for (a = 0; a < 3; a++) {
        if (!(fabs(ray->org[a]) < limit && fabs(p->origin[a]) + (double)p->res * p->cell < limit))
            return 0;
        g[a] = ((double)ray->org[a] - p->origin[a]) / p->cell;
        gd[a] = (double)ray->dir[a] / p->cell;
        moving = max2(moving, fabs(gd[a]));
    }
    return moving > 0;
}

int brt_inner_occludes(const brt_svdag *dag, const brt_proxy *inner, const brt_ray *ray)
{
    double g[3], gd[3], t, tend = INFINITY, nudge = 0;
    int levels = tree_levels(inner->res), a, step;
    if (inner->root == BRT_EMPTY_ROOT || !inner_frame(inner, ray, g, gd)) return 0;
    t = ray->tnear;
    for (a = 0; a < 3; a++) {
        slab(g[a], gd[a], 0, inner->res, &t, &tend);
        nudge = max2(nudge, fabs(gd[a]));
    }
    nudge = 0x1p-30 / nudge;   /* a billionth of a voxel */
    /* Walk the voxels and empty nodes along the ray; a node missed through
    ** rounding only loses a chance to stop the ray (never a wrong answer). */
    for (step = 0; t < tend && step < 8 * (int)inner->res + 64; step++) {
        uint32_t at[3], side;
        double exit = INFINITY;
        int size;
        for (a = 0; a < 3; a++) {
            /* t lies in the grid's slab interval; a point rounded just
            ** outside it belongs to the border voxel. */
            double q = g[a] + t * gd[a], f = gd[a] < 0 ? ceil(q) - 1 : floor(q);
            at[a] = f < 0 ? 0 : f >= inner->res ? inner->res - 1 : (uint32_t)f;
        }
        size = inner_lookup(dag, inner->root, levels, at);
        if (size < 0 && core_holds(g, gd, at, ray->tnear)) return 1;
        side = 1u << (size < 0 ? 0 : size);
        for (a = 0; a < 3; a++) {
            double lo = at[a] & ~(side - 1);
            if (gd[a] != 0) exit = min2(exit, ((gd[a] > 0 ? lo + side : lo) - g[a]) / gd[a]);
        }
        t = max2(exit, t) + nudge;
    }
    return 0;
}
