/*
** tests/test_svdag.c -- conservative voxel proxies (svdag.c) against
** independent oracles:
**   - the voxelizer against an exact separating-axis test in integers, on
**     triangles whose vertices lie on a quarter-cell lattice;
**   - DAG decode against the dense grid, and SVO node counts against a
**     count of non-empty blocks, at every resolution 2..1024;
**   - the ray cast against a brute-force slab test over all set voxels,
**     and (the other side) against the same test on voxels grown by twice
**     the growth svdag.c documents: a proxy hit must be near a set voxel,
**     and its entry not before the grown voxels' entry;
**   - END TO END: every ray that hits a triangle (BVH or brute force over
**     brt_intersect_triangle) hits the proxy no later than the triangle;
**   - dedup across proxies, blob round trip, corrupt blobs.
** Conservativeness is one-sided: a false miss (or a late entry) fails; a
** false hit is only counted and printed.
*/
#include "test.h"
#include "util.h"
#include "batchrt.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>

/* ===================================================================== */
/* Helpers                                                               */
/* ===================================================================== */

static uint32_t rand_below(uint64_t *rng, uint32_t n)
{
    return (uint32_t)(brt_random_u64(rng) % n);
}

static float rand_range(uint64_t *rng, float lo, float hi)
{
    return lo + (hi - lo) * brt_random_float(rng);
}

/* An empty grid with an exact frame (origin, cell) chosen by the test. */
static void grid_exact(brt_grid *grid, uint32_t res, const float origin[3],
                       float cell)
{
    float bmin[3] = {0, 0, 0}, bmax[3] = {1, 1, 1};
    brt_grid_init(grid, bmin, bmax, res);
    memcpy(grid->origin, origin, sizeof grid->origin);
    grid->cell = cell;
}

static void grid_clear(brt_grid *grid)
{
    size_t n = ((size_t)grid->res * grid->res * grid->res + 63) / 64;
    memset(grid->bits, 0, n * sizeof(uint64_t));
}

static void mesh_bounds(const float *pos, uint32_t vertex_count, float bmin[3],
                        float bmax[3])
{
    uint32_t v;
    int i;
    for (i = 0; i < 3; i++) { bmin[i] = INFINITY; bmax[i] = -INFINITY; }
    for (v = 0; v < vertex_count; v++)
        for (i = 0; i < 3; i++) {
            bmin[i] = fminf(bmin[i], pos[3 * v + i]);
            bmax[i] = fmaxf(bmax[i], pos[3 * v + i]);
        }
}

/* ===================================================================== */
/* Grid frame                                                            */
/* ===================================================================== */

static void test_grid_frame(void)
{
    static const float boxes[][6] = {
        {0, 0, 0, 1, 1, 1}, {-3, 2, 7, 5, 2.5f, 7}, {1e5f, 1e5f, 1e5f, 100001, 100000.5f, 100002},
        {-1e-3f, 0, 0, 1e-3f, 1e-7f, 3e-4f}, {5, 5, 5, 5, 5, 5}, {0, 0, 0, 0, 0, 0},
        {-3e38f, 0, 0, 3e38f, 1, 1}};
    size_t b;
    uint32_t res;
    brt_grid grid;
    float lo[3] = {0, 0, 0}, hi[3] = {1, 1, 1}, nan_box[3] = {0, NAN, 0};
    for (b = 0; b < sizeof boxes / sizeof boxes[0]; b++)
        for (res = 2; res <= 1024; res *= 2) {
            const float *bmin = boxes[b], *bmax = boxes[b] + 3;
            int i;
            if (brt_grid_init(&grid, bmin, bmax, res) != BRT_OK) {
                EXPECT(b == 6, "box %d res %u refused", (int)b, res);
                continue;
            }
            for (i = 0; i < 3; i++) {
                /* The closed grid covers the box, in exact arithmetic. */
                EXPECT(grid.origin[i] <= bmin[i], "box %d origin", (int)b);
                EXPECT((long double)grid.origin[i] + (long double)grid.cell * res >= bmax[i],
                       "box %d res %u axis %d not covered", (int)b, res, i);
            }
            EXPECT(grid.cell > 0 && brt_grid_count(&grid) == 0, "box %d cell", (int)b);
            brt_grid_free(&grid);
        }
    EXPECT(brt_grid_init(&grid, lo, hi, 3) == BRT_EARG, "res 3 accepted");
    EXPECT(brt_grid_init(&grid, lo, hi, 1) == BRT_EARG, "res 1 accepted");
    EXPECT(brt_grid_init(&grid, lo, hi, 2048) == BRT_EARG, "res 2048 accepted");
    EXPECT(brt_grid_init(&grid, hi, lo, 8) == BRT_EARG, "inverted box accepted");
    EXPECT(brt_grid_init(&grid, lo, nan_box, 8) == BRT_EARG, "NaN box accepted");
}

/* ===================================================================== */
/* Voxelizer against an exact integer SAT                                */
/* ===================================================================== */

/* Exact closed triangle/box overlap; coordinates in quarter cells, the
** box is [4x, 4x+4] per axis.  Separating-axis test of Akenine-Moller, but
** projecting all 8 box corners instead of using a radius. */
static int oracle_axis_separates(int64_t v[3][3], const int64_t box[3],
                                 const int64_t a[3])
{
    int64_t tmin = INT64_MAX, tmax = INT64_MIN, bmin = INT64_MAX, bmax = INT64_MIN;
    int k;
    for (k = 0; k < 3; k++) {
        int64_t p = a[0] * v[k][0] + a[1] * v[k][1] + a[2] * v[k][2];
        if (p < tmin) tmin = p;
        if (p > tmax) tmax = p;
    }
    for (k = 0; k < 8; k++) {
        int64_t p = a[0] * (box[0] + 4 * (k & 1)) + a[1] * (box[1] + 4 * ((k >> 1) & 1)) +
                    a[2] * (box[2] + 4 * (k >> 2));
        if (p < bmin) bmin = p;
        if (p > bmax) bmax = p;
    }
    return tmax < bmin || bmax < tmin;
}

static int oracle_overlap(int64_t v[3][3], uint32_t x, uint32_t y, uint32_t z)
{
    int64_t box[3], e[3][3], a[3];
    int k, i, j;
    box[0] = 4 * (int64_t)x; box[1] = 4 * (int64_t)y; box[2] = 4 * (int64_t)z;
    for (k = 0; k < 3; k++)
        for (i = 0; i < 3; i++) e[k][i] = v[(k + 1) % 3][i] - v[k][i];
    for (i = 0; i < 3; i++) {             /* box normals */
        a[0] = i == 0; a[1] = i == 1; a[2] = i == 2;
        if (oracle_axis_separates(v, box, a)) return 0;
    }
    a[0] = e[0][1] * e[1][2] - e[0][2] * e[1][1];   /* triangle normal */
    a[1] = e[0][2] * e[1][0] - e[0][0] * e[1][2];
    a[2] = e[0][0] * e[1][1] - e[0][1] * e[1][0];
    if (oracle_axis_separates(v, box, a)) return 0;
    for (k = 0; k < 3; k++)                           /* edge x box axis */
        for (j = 0; j < 3; j++) {
            int64_t u[3] = {0, 0, 0};
            u[j] = 1;
            a[0] = e[k][1] * u[2] - e[k][2] * u[1];
            a[1] = e[k][2] * u[0] - e[k][0] * u[2];
            a[2] = e[k][0] * u[1] - e[k][1] * u[0];
            if (oracle_axis_separates(v, box, a)) return 0;
        }
    return 1;
}

/* A lattice coordinate in quarter cells over [-4, 4 res + 4]. */
static int64_t lattice(uint64_t *rng, uint32_t res, int snap)
{
    int64_t q = (int64_t)rand_below(rng, 4 * res + 9) - 4;
    return snap ? q / snap * snap : q;
}

/* Random and adversarial lattice triangles: corners, faces, axis-aligned,
** slivers, collinear, points, tiny ones inside one voxel. */
static void lattice_triangle(uint64_t *rng, uint32_t res, int64_t v[3][3])
{
    int kind = (int)rand_below(rng, 8), k, i, axis = (int)rand_below(rng, 3);
    int snap = kind == 1 ? 4 : kind == 2 ? 2 : 0;
    for (k = 0; k < 3; k++)
        for (i = 0; i < 3; i++) v[k][i] = lattice(rng, res, snap);
    switch (kind) {
    case 3:   /* axis-aligned, on a voxel face plane */
        for (k = 0; k < 3; k++) v[k][axis] = v[0][axis] / 4 * 4;
        break;
    case 4:   /* collinear: v2 = v0 + m (v1 - v0), or a sliver off it */
        for (i = 0; i < 3; i++) {
            int64_t d = (v[1][i] - v[0][i]) / 4;
            v[1][i] = v[0][i] + d;
            v[2][i] = v[0][i] + 3 * d + (i == axis ? (int64_t)rand_below(rng, 3) - 1 : 0);
        }
        break;
    case 5:   /* two or three equal vertices */
        memcpy(v[1], v[0], sizeof v[0]);
        if (rand_below(rng, 2)) memcpy(v[2], v[0], sizeof v[0]);
        break;
    case 6:   /* small, near one voxel corner */
        for (k = 1; k < 3; k++)
            for (i = 0; i < 3; i++) v[k][i] = v[0][i] + (int64_t)rand_below(rng, 5) - 2;
        break;
    case 7:   /* an edge lying along a voxel edge */
        for (i = 0; i < 3; i++) v[0][i] = v[0][i] / 4 * 4;
        memcpy(v[1], v[0], sizeof v[0]);
        v[1][axis] += 4 * (int64_t)rand_below(rng, 3) + 4;
        break;
    default:
        break;
    }
}

static void check_voxelizer_frame(const float origin[3], float cell, uint32_t res,
                                  int triangles, uint64_t *rng, uint64_t *extra,
                                  uint64_t *set)
{
    brt_grid grid;
    uint32_t idx[3] = {0, 1, 2}, x, y, z;
    int t, k, i;
    grid_exact(&grid, res, origin, cell);
    for (t = 0; t < triangles && !test_failed(); t++) {
        int64_t v[3][3];
        float pos[9];
        lattice_triangle(rng, res, v);
        for (k = 0; k < 3; k++)
            for (i = 0; i < 3; i++) pos[3 * k + i] = origin[i] + cell * (float)v[k][i] * 0.25f;
        grid_clear(&grid);
        CHECK(brt_voxelize(&grid, pos, idx, 1) == BRT_OK, "voxelize failed");
        for (z = 0; z < res; z++)
            for (y = 0; y < res; y++)
                for (x = 0; x < res; x++) {
                    int want = oracle_overlap(v, x, y, z), got = brt_grid_get(&grid, x, y, z);
                    if (want && !got)
                        test_fail_at(__FILE__, __LINE__,
                                     "frame origin %g cell %g: missed voxel (%u,%u,%u) of triangle (%lld,%lld,%lld) "
                                     "(%lld,%lld,%lld) (%lld,%lld,%lld) /4 cells",
                                     origin[0], cell, x, y, z, (long long)v[0][0], (long long)v[0][1],
                                     (long long)v[0][2], (long long)v[1][0], (long long)v[1][1],
                                     (long long)v[1][2], (long long)v[2][0], (long long)v[2][1],
                                     (long long)v[2][2]);
                    *extra += got && !want;
                    *set += want;
                }
    }
    brt_grid_free(&grid);
}

static void test_voxelizer_exact(void)
{
    /* Frames where origin + cell * (k/4) is exact in float. */
    static const float origins[3][3] = {{0, 0, 0}, {-1024, 96, 4096}, {1e5f, -2e5f, 0.5f}};
    static const float cells[3] = {1, 0.5f, 0.125f};
    uint64_t rng = test_seed(), extra = 0, set = 0;
    int f;
    for (f = 0; f < 3 && !test_failed(); f++)
        check_voxelizer_frame(origins[f], cells[f], 8, 6000, &rng, &extra, &set);
    printf("  svdag: voxelizer: %llu voxels set by the oracle, %llu extra (%.3f%%)\n",
           (unsigned long long)set, (unsigned long long)extra, set ? 100.0 * extra / set : 0.0);
}

/* ---- non-lattice triangles ------------------------------------------- */

/* Expects every voxel whose closed box contains the point p (world
** coordinates, a point of the triangle) to be set.  Voxel bounds
** origin + x cell are exact in double in the frames used here. */
static int voxels_at_point_set(const brt_grid *grid, const float p[3])
{
    uint32_t lo[3], hi[3], x, y, z;
    int i;
    for (i = 0; i < 3; i++) {
        const double q = ((double)p[i] - grid->origin[i]) / grid->cell;
        double k = floor(q);
        if (k > grid->res - 1.0) k = grid->res - 1.0;
        lo[i] = hi[i] = (uint32_t)k;
        if ((double)grid->origin[i] + k * (double)grid->cell == (double)p[i] && k > 0) lo[i]--;
    }
    for (z = lo[2]; z <= hi[2]; z++)
        for (y = lo[1]; y <= hi[1]; y++)
            for (x = lo[0]; x <= hi[0]; x++)
                if (!brt_grid_get(grid, x, y, z)) return 0;
    return 1;
}

/* A world point origin + k cell that is a float, with k an interior
** lattice coordinate, found by trying; 0 when none came up. */
static int lattice_float(uint64_t *rng, const brt_grid *grid, int axis, float *out)
{
    int tries;
    for (tries = 0; tries < 50; tries++) {
        const double w = grid->origin[axis] + (double)(1 + rand_below(rng, grid->res - 1)) * grid->cell;
        if ((double)(float)w == w) {
            *out = (float)w;
            return 1;
        }
    }
    return 0;
}

/* Triangles with full-mantissa vertices (so that the voxelizer's dot
** products round, unlike on lattice vertices) and one point exactly on a
** voxel corner, edge or face: a vertex there, or the midpoint of an edge
** (v2 = 2 L - v1, kept when exact).  The voxels around that point are
** touched only at it, and must all be set: this is what the voxelizer's
** rounding growth is for. */
static void test_voxelizer_non_lattice(void)
{
    static const float origins[3][3] = {{0, 0, 0}, {0, 0, 0}, {-1024, 96, 4096}};
    static const float cells[3] = {1, 0.1f, 0.5f};
    const uint32_t res = 8, idx[3] = {0, 1, 2};
    uint64_t rng = test_seed() + 11, checked = 0;
    int f, n;
    for (f = 0; f < 3 && !test_failed(); f++) {
        brt_grid grid;
        grid_exact(&grid, res, origins[f], cells[f]);
        for (n = 0; n < 4000 && !test_failed(); n++) {
            const int midpoint = n & 1, on_lattice = (int)rand_below(&rng, 4);
            float v[3][3], point[3];
            int k, i, ok = 1;
            for (k = 0; k < 3; k++)
                for (i = 0; i < 3; i++)
                    v[k][i] = grid.origin[i] + grid.cell * rand_range(&rng, 0.0f, (float)res);
            /* the point: on a corner (on_lattice 3), else on an edge or face */
            for (i = 0; i < 3 && ok; i++)
                if (i < on_lattice || on_lattice == 3) ok = lattice_float(&rng, &grid, i, &point[i]);
                else point[i] = v[0][i];
            if (!ok) continue;
            for (i = 0; i < 3; i++) {
                if (!midpoint) {
                    v[0][i] = point[i];
                    continue;
                }
                v[2][i] = 2.0f * point[i] - v[1][i];
                if ((double)v[2][i] != 2.0 * point[i] - (double)v[1][i]) ok = 0;
            }
            if (!ok) continue;
            grid_clear(&grid);
            CHECK(brt_voxelize(&grid, &v[0][0], idx, 1) == BRT_OK, "voxelize failed");
            checked++;
            EXPECT(voxels_at_point_set(&grid, point),
                   "frame %d: a voxel at (%a %a %a), a point of the triangle (%a %a %a) (%a %a %a) "
                   "(%a %a %a), is not set", f, point[0], point[1], point[2], v[0][0], v[0][1],
                   v[0][2], v[1][0], v[1][1], v[1][2], v[2][0], v[2][1], v[2][2]);
        }
        brt_grid_free(&grid);
    }
    EXPECT(checked > 3000, "only %llu triangles checked", (unsigned long long)checked);
}

static void test_voxelizer_input(void)
{
    brt_grid grid;
    float pos[9] = {0, 0, 0, 1, 0, 0, NAN, 1, 0}, origin[3] = {0, 0, 0};
    uint32_t idx[3] = {0, 1, 2};
    grid_exact(&grid, 4, origin, 1);
    EXPECT(brt_voxelize(&grid, pos, idx, 1) == BRT_EARG, "NaN vertex accepted");
    pos[6] = 100; pos[7] = 100; pos[8] = 100;   /* a triangle crossing the grid */
    EXPECT(brt_voxelize(&grid, pos, idx, 1) == BRT_OK && brt_grid_get(&grid, 0, 0, 0) &&
               brt_grid_get(&grid, 3, 3, 3),
           "triangle reaching outside the grid not clipped");
    grid.cell = 0;
    EXPECT(brt_voxelize(&grid, pos, idx, 1) == BRT_EARG, "zero cell accepted");
    brt_grid_free(&grid);
}

/* ===================================================================== */
/* DAG decode and node counts                                             */
/* ===================================================================== */

/* Random voxels: dense for small grids, sparse clusters and a slab for
** large ones (so that 1024^3 stays quick). */
static void fill_random(brt_grid *grid, uint64_t *rng)
{
    uint32_t res = grid->res, n, i, x, y;
    if (res <= 32) {
        uint32_t density = 1 + rand_below(rng, 40);
        for (i = 0; i < res * res * res; i++)
            if (rand_below(rng, 100) < density)
                brt_grid_set(grid, i % res, (i / res) % res, i / (res * res));
        return;
    }
    n = 2000 + rand_below(rng, 2000);
    for (i = 0; i < n; i++) {
        uint32_t cx = rand_below(rng, res), cy = rand_below(rng, res), cz = rand_below(rng, res);
        brt_grid_set(grid, cx, cy, cz);
        brt_grid_set(grid, cx + 1, cy, cz);
        brt_grid_set(grid, cx, cy + 1, cz + 1);
    }
    for (y = 0; y < res; y += 3)                      /* a plane with holes */
        for (x = 0; x < res; x += 1 + (x & 1)) brt_grid_set(grid, x, y, res / 3);
}

/* Non-empty blocks of 2^l voxels for l = 2..levels (the grid padded to
** 4^3 when res is 2): the SVO's node count, counted on the dense grid. */
static uint64_t count_blocks(const brt_grid *grid)
{
    uint32_t n = grid->res < 4 ? 4 : grid->res, l, x, y, z, i;
    unsigned char *marks[12] = {NULL};
    uint64_t total = 0;
    for (l = 2; (1u << l) <= n; l++) {
        uint32_t m = n >> l;
        marks[l] = (unsigned char *)calloc((size_t)m * m * m, 1);
        if (!marks[l]) return 0;
    }
    for (z = 0; z < grid->res; z++)
        for (y = 0; y < grid->res; y++)
            for (x = 0; x < grid->res; x++)
                if (brt_grid_get(grid, x, y, z))
                    for (l = 2; marks[l]; l++) {
                        uint32_t m = n >> l;
                        marks[l][(x >> l) + m * ((y >> l) + (size_t)m * (z >> l))] = 1;
                    }
    for (l = 2; marks[l]; l++) {
        uint32_t m = n >> l;
        for (i = 0; i < m * m * m; i++) total += marks[l][i];
        free(marks[l]);
    }
    return total;
}

static void test_decode_every_resolution(void)
{
    brt_svdag *dag;
    brt_error err;
    uint64_t rng = test_seed() + 1;
    uint32_t res;
    int round;
    CHECK(brt_svdag_create(&dag) == BRT_OK, "create");
    for (round = 0; round < 2; round++)
        for (res = 2; res <= 1024; res *= 2) {
            brt_grid grid, back;
            brt_proxy proxy;
            float origin[3] = {1, 2, 3};
            size_t words = ((size_t)res * res * res + 63) / 64;
            grid_exact(&grid, res, origin, 0.5f);
            if (round == 1 || res <= 256) fill_random(&grid, &rng);
            EXPECT(brt_svdag_add(dag, &grid, &proxy) == BRT_OK, "add res %u", res);
            EXPECT(brt_svdag_check(dag, &err) == BRT_OK, "check res %u: %s", res, err.message);
            EXPECT(brt_proxy_check(dag, &proxy, &err) == BRT_OK, "proxy res %u: %s", res, err.message);
            EXPECT((proxy.root == BRT_EMPTY_ROOT) == (brt_grid_count(&grid) == 0), "empty root res %u", res);
            EXPECT(brt_svdag_decode(dag, &proxy, &back) == BRT_OK &&
                       memcmp(grid.bits, back.bits, words * 8) == 0 && back.res == res &&
                       back.cell == grid.cell && back.origin[2] == grid.origin[2],
                   "decode differs at res %u", res);
            if (res <= 256)
                EXPECT(brt_svdag_svo_nodes(dag, &proxy) == count_blocks(&grid),
                       "svo nodes at res %u: %llu, blocks %llu", res,
                       (unsigned long long)brt_svdag_svo_nodes(dag, &proxy),
                       (unsigned long long)count_blocks(&grid));
            brt_grid_free(&back);
            brt_grid_free(&grid);
        }
    brt_svdag_free(dag);
}

/* ===================================================================== */
/* Ray cast against brute force                                           */
/* ===================================================================== */

/* Entry of a ray into a closed box, in double; 0 when it misses. */
static int oracle_box(const brt_ray *ray, const double lo[3], const double hi[3],
                      double tnear, double tfar, double *t)
{
    double enter = tnear, leave = tfar;
    int i;
    for (i = 0; i < 3; i++) {
        double o = ray->org[i], d = ray->dir[i];
        if (d == 0) {
            if (o < lo[i] || o > hi[i]) return 0;
        } else {
            double a = (lo[i] - o) / d, b = (hi[i] - o) / d;
            enter = fmax(enter, fmin(a, b));
            leave = fmin(leave, fmax(a, b));
        }
    }
    *t = enter;
    return enter <= leave;
}

/* Entry of the ray's segment into voxel c of the grid, its closed box
** grown by grow cells on every side; 0 when it misses. */
static int oracle_voxel(const brt_grid *grid, const uint32_t c[3], const brt_ray *ray,
                        double grow, double *t)
{
    double lo[3], hi[3];
    int i;
    for (i = 0; i < 3; i++) {
        lo[i] = grid->origin[i] + (double)grid->cell * (c[i] - grow);
        hi[i] = grid->origin[i] + (double)grid->cell * (c[i] + 1 + grow);
    }
    return oracle_box(ray, lo, hi, ray->tnear, ray->tfar, t);
}

/* First touched set voxel over all voxels of the grid, each grown by grow
** cells on every side. */
static int oracle_grid(const brt_grid *grid, const brt_ray *ray, double grow,
                       double *t_best)
{
    uint32_t x, y, z, c[3];
    int hit = 0;
    for (z = 0; z < grid->res; z++)
        for (y = 0; y < grid->res; y++)
            for (x = 0; x < grid->res; x++) {
                double t;
                if (!brt_grid_get(grid, x, y, z)) continue;
                c[0] = x; c[1] = y; c[2] = z;
                if (oracle_voxel(grid, c, ray, grow, &t) && (!hit || t < *t_best)) {
                    *t_best = t;
                    hit = 1;
                }
            }
    return hit;
}

/* A = (max |o_i| + max |origin_i|) / (N cell) + 1 of svdag.c's growth:
** the largest world |coordinate| of the ray's origin and of the root
** cube, in root-cube units. */
static double world_term(const float org[3], const float origin[3], double n, float cell)
{
    double o = 0, c = 0;
    int i;
    for (i = 0; i < 3; i++) {
        o = fmax(o, fabs(org[i]));
        c = fmax(c, fabs(origin[i]));
    }
    return (o + c) / (n * cell) + 1;
}

/* Twice the box growth of brt_proxy_raycast, in cells: g = 2^-18 (P + 3 +
** A) in units of the root cube (N = 2^levels cells, levels >= 2), where P
** is the largest |coordinate| of the (mirrored) origin in the [1,2] frame,
** at most |1 + (o - origin) / (N cell)| + 3, and A is world_term. */
static double documented_grow(const brt_grid *grid, const brt_ray *ray)
{
    double n = grid->res < 4 ? 4 : grid->res, p = 0;
    int i;
    for (i = 0; i < 3; i++)
        p = fmax(p, fabs(1 + (ray->org[i] - (double)grid->origin[i]) / (n * grid->cell)) + 3);
    return 2 * 0x1p-18 * (p + 3 + world_term(ray->org, grid->origin, n, grid->cell)) * n;
}

/* The box growth of brt_proxy_raycast exactly as svdag.c states it, in
** cells: g = 2^-18 (P + 3 + A) root-cube units, P the largest |coordinate|
** of the mirrored origin in the [1,2] frame, computed as the cast computes
** it (root cube of N = 2^levels cells, levels >= 2), A world_term. */
static double stated_grow(const brt_proxy *proxy, const brt_ray *ray)
{
    const double n = proxy->res < 4 ? 4 : proxy->res, scale = (1.0 / n) / proxy->cell;
    double pmax = 0;
    int i;
    for (i = 0; i < 3; i++) {
        double p = 1.0 + ((double)ray->org[i] - proxy->origin[i]) * scale;
        if (ray->dir[i] * scale > 0) p = 3.0 - p;
        pmax = fmax(pmax, fabs(p));
    }
    return 0x1p-18 * (pmax + 3 + world_term(ray->org, proxy->origin, n, proxy->cell)) * n;
}

/* Oracle-friendly rays in cell units: random, axis-parallel, grazing along
** voxel faces, through lattice corners, from far away. */
static void lattice_ray(uint64_t *rng, const brt_grid *grid, brt_ray *ray)
{
    float res = (float)grid->res;
    int kind = (int)rand_below(rng, 5), i, axis = (int)rand_below(rng, 3);
    float o[3], d[3];
    for (i = 0; i < 3; i++) {
        o[i] = rand_range(rng, -1, res + 1);
        d[i] = rand_range(rng, -1, 1);
    }
    switch (kind) {
    case 1:   /* axis-parallel, origin on quarter points */
        for (i = 0; i < 3; i++) { o[i] = floorf(o[i] * 4) / 4; d[i] = 0; }
        d[axis] = rand_below(rng, 2) ? 1.5f : -0.75f;
        break;
    case 2:   /* grazing: in a voxel face plane */
        o[axis] = floorf(o[axis]);
        d[axis] = 0;
        break;
    case 3:   /* through lattice corners */
        for (i = 0; i < 3; i++) {
            o[i] = floorf(o[i]);
            d[i] = (float)((int)rand_below(rng, 5) - 2);
        }
        if (d[0] == 0 && d[1] == 0 && d[2] == 0) d[axis] = 1;
        break;
    case 4:   /* from far away, aimed at the grid */
        for (i = 0; i < 3; i++) {
            d[i] = rand_range(rng, 0, res) - o[i] * 1e5f;
            o[i] *= 1e5f;
        }
        break;
    default:
        break;
    }
    for (i = 0; i < 3; i++) {
        ray->org[i] = grid->origin[i] + grid->cell * o[i];
        ray->dir[i] = grid->cell * d[i];
    }
    ray->tnear = rand_below(rng, 3) ? 0 : rand_range(rng, 0, 2);
    ray->tfar = rand_below(rng, 3) ? INFINITY : ray->tnear + (float)rand_below(rng, 8) * 0.5f;
}

/*
** The readable reference cast (brt_proxy_raycast_reference) on a ray the
** fast cast answered with (got, t_got): it must be conservative on its own
** -- a hit at or before t_want when the oracle hits (want) -- and agree
** with the fast cast: the same hit or miss, with and without an entry
** wanted, and the same entry.  The two compute the same plane distances
** and take the least entry over the same touched voxels, only in another
** order, so the entries are equal, not just both valid lower bounds.
** Returns 0 after reporting a failure.
*/
static int check_reference_cast(const brt_svdag *dag, const brt_proxy *proxy, const brt_ray *ray,
                                int got, float t_got, int want, double t_want)
{
    float t_ref = 0;
    int ref = brt_proxy_raycast_reference(dag, proxy, ray, ray->tnear, ray->tfar, &t_ref);
    int ref_any = brt_proxy_raycast_reference(dag, proxy, ray, ray->tnear, ray->tfar, NULL);
    if (want && !(ref && t_ref <= t_want && t_ref >= ray->tnear)) {
        test_fail_at(__FILE__, __LINE__, "reference cast: ray (%a %a %a) dir (%a %a %a) [%a %a]: "
                     "oracle hit at t %a, reference %d t %a", ray->org[0], ray->org[1], ray->org[2],
                     ray->dir[0], ray->dir[1], ray->dir[2], ray->tnear, ray->tfar, t_want, ref, t_ref);
        return 0;
    }
    if (ref != got || ref_any != got || (got && t_ref != t_got)) {
        test_fail_at(__FILE__, __LINE__, "reference and fast cast differ: ray (%a %a %a) dir (%a %a %a) "
                     "[%a %a]: reference %d (yes/no %d) t %a, fast %d t %a", ray->org[0], ray->org[1],
                     ray->org[2], ray->dir[0], ray->dir[1], ray->dir[2], ray->tnear, ray->tfar, ref,
                     ref_any, t_ref, got, t_got);
        return 0;
    }
    return 1;
}

static void test_raycast_oracle(void)
{
    static const float origins[2][3] = {{0, 0, 0}, {-3.5f, 100, 1e4f}};
    static const float cells[2] = {1, 0.125f};
    brt_svdag *dag;
    uint64_t rng = test_seed() + 2, hits = 0, false_hits = 0, rays = 0;
    uint32_t res;
    int f, n;
    CHECK(brt_svdag_create(&dag) == BRT_OK, "create");
    for (f = 0; f < 2; f++)
        for (res = 2; res <= 16 && !test_failed(); res *= 2) {
            brt_grid grid;
            brt_proxy proxy;
            grid_exact(&grid, res, origins[f], cells[f]);
            fill_random(&grid, &rng);
            CHECK(brt_svdag_add(dag, &grid, &proxy) == BRT_OK, "add");
            for (n = 0; n < 6000 && !test_failed(); n++) {
                brt_ray ray;
                double t_oracle = 0, t_grown = 0, t_stated = 0;
                float t_entry;
                int want, near, got, stated;
                lattice_ray(&rng, &grid, &ray);
                want = oracle_grid(&grid, &ray, 0, &t_oracle);
                near = oracle_grid(&grid, &ray, documented_grow(&grid, &ray), &t_grown);
                /* Boxes grown by the stated g, less 2^-20 of it: more than
                ** the cast's rounding (a few 2^-53 (P + 3)) and the oracle's,
                ** far less than an ulp of t. */
                stated = oracle_grid(&grid, &ray, stated_grow(&proxy, &ray) * (1 - 0x1p-20), &t_stated);
                got = brt_proxy_raycast(dag, &proxy, &ray, ray.tnear, ray.tfar, &t_entry);
                check_reference_cast(dag, &proxy, &ray, got, t_entry, want, t_oracle);
                rays++;
                /* the yes/no cast (no entry wanted) stops early, same answer */
                EXPECT(brt_proxy_raycast(dag, &proxy, &ray, ray.tnear, ray.tfar, NULL) == got,
                       "res %u ray (%a %a %a) dir (%a %a %a): cast without entry disagrees",
                       res, ray.org[0], ray.org[1], ray.org[2], ray.dir[0], ray.dir[1], ray.dir[2]);
                hits += want;
                false_hits += got && !want;
                EXPECT(!want || (got && t_entry <= t_oracle && t_entry >= ray.tnear),
                       "res %u ray (%a %a %a) dir (%a %a %a) [%a %a]: oracle t %a, proxy %d t %a",
                       res, ray.org[0], ray.org[1], ray.org[2], ray.dir[0], ray.dir[1],
                       ray.dir[2], ray.tnear, ray.tfar, t_oracle, got, t_entry);
                /* the stated bound: every box grown by g is reported, and
                ** entered no earlier than the entry (rounded down) */
                EXPECT(!stated || (got && t_entry <= t_stated),
                       "res %u ray (%a %a %a) dir (%a %a %a) [%a %a]: entry of the voxels grown by "
                       "the stated g %a, proxy %d t %a", res, ray.org[0], ray.org[1], ray.org[2],
                       ray.dir[0], ray.dir[1], ray.dir[2], ray.tnear, ray.tfar, t_stated, got, t_entry);
                /* the other side: float rounding of the entry allowed */
                EXPECT(!got || (near && t_entry >= nextafterf((float)t_grown, -INFINITY)),
                       "res %u ray (%a %a %a) dir (%a %a %a) [%a %a]: proxy t %a, no set voxel "
                       "grown by %g cells touched before (%d, t %a)",
                       res, ray.org[0], ray.org[1], ray.org[2], ray.dir[0], ray.dir[1],
                       ray.dir[2], ray.tnear, ray.tfar, t_entry,
                       documented_grow(&grid, &ray), near, t_grown);
            }
            brt_grid_free(&grid);
        }
    printf("  svdag: raycast: %llu rays, %llu oracle hits, %llu false hits\n",
           (unsigned long long)rays, (unsigned long long)hits, (unsigned long long)false_hits);
    brt_svdag_free(dag);
}

static void test_raycast_special(void)
{
    brt_svdag *dag;
    brt_grid grid;
    brt_proxy proxy, empty, bad;
    float origin[3] = {0, 0, 0}, t;
    brt_ray ray = {{-5, 0.5f, 0.5f}, {1, 0, 0}, 0, INFINITY};
    CHECK(brt_svdag_create(&dag) == BRT_OK, "create");
    grid_exact(&grid, 8, origin, 1);
    brt_grid_set(&grid, 3, 0, 0);
    CHECK(brt_svdag_add(dag, &grid, &proxy) == BRT_OK, "add");
    grid_clear(&grid);
    CHECK(brt_svdag_add(dag, &grid, &empty) == BRT_OK && empty.root == BRT_EMPTY_ROOT, "empty");
    EXPECT(brt_proxy_raycast(dag, &proxy, &ray, 0, INFINITY, &t) && t <= 8 && t > 7.9f,
           "axis ray: t %g", t);
    EXPECT(brt_proxy_raycast(dag, &proxy, &ray, 1, 7.5f, &t) == 0, "segment before the voxel hit");
    EXPECT(brt_proxy_raycast(dag, &proxy, &ray, 8.5f, 8.6f, &t) && t == 8.5f, "start inside: t %g", t);
    EXPECT(brt_proxy_raycast(dag, &proxy, &ray, 3, 2, &t) == 0, "empty segment hit");
    EXPECT(brt_proxy_raycast(dag, &empty, &ray, 0, INFINITY, &t) == 0, "empty proxy hit");
    ray.dir[1] = NAN;
    EXPECT(brt_proxy_raycast(dag, &proxy, &ray, 0.25f, 1, &t) == 1 && t == 0.25f, "NaN ray");
    ray.dir[1] = 0;
    EXPECT(brt_proxy_raycast(dag, &proxy, &ray, NAN, 1, &t) == 1, "NaN tnear");
    bad = proxy;
    bad.root = 12345;
    EXPECT(brt_proxy_check(dag, &bad, NULL) == BRT_ECHECK, "bad root passes the check");
    bad = proxy;
    bad.res = 16;
    EXPECT(brt_proxy_check(dag, &bad, NULL) == BRT_ECHECK, "wrong depth passes the check");
    bad.res = 12;
    EXPECT(brt_proxy_check(dag, &bad, NULL) == BRT_ECHECK, "res 12 passes the check");
    brt_grid_free(&grid);
    brt_svdag_free(dag);
}

/* ===================================================================== */
/* End to end: triangles hit => proxy hit, no later                       */
/* ===================================================================== */

typedef struct soup {
    float *pos;
    uint32_t *idx;
    uint32_t vertex_count, tri_count;
} soup;

static void soup_free(soup *s)
{
    free(s->pos);
    free(s->idx);
    memset(s, 0, sizeof *s);
}

/* A mesh from the shared data, scaled and moved; 0 when absent. */
static int soup_load(const char *name, float scale, float offset, soup *s)
{
    const char *path = test_shared_mesh(name);
    brt_mesh mesh;
    brt_error err;
    uint32_t i;
    if (!path || brt_mesh_load(path, &mesh, &err) != BRT_OK) return 0;
    for (i = 0; i < 3 * mesh.vertex_count; i++)
        mesh.positions[i] = mesh.positions[i] * scale + offset;
    s->pos = mesh.positions;
    s->idx = mesh.indices;
    s->vertex_count = mesh.vertex_count;
    s->tri_count = mesh.triangle_count;
    return 1;
}

/* Adversarial: axis-aligned triangles lying in voxel face planes of a
** res^3 grid over [0,res]^3 (cell 1), edges along voxel edges, slivers,
** degenerate ones; corner vertices pin the bounds to the whole grid. */
static void soup_on_faces(uint64_t *rng, uint32_t res, uint32_t count, soup *s)
{
    uint32_t t, k;
    s->vertex_count = 3 * count;
    s->tri_count = count;
    s->pos = (float *)malloc(9 * (size_t)count * sizeof(float));
    s->idx = (uint32_t *)malloc(3 * (size_t)count * sizeof(uint32_t));
    for (t = 0; t < count; t++) {
        int axis = (int)rand_below(rng, 3), i;
        float plane = (float)rand_below(rng, res + 1);
        float *v = s->pos + 9 * t;
        for (k = 0; k < 3; k++) {
            for (i = 0; i < 3; i++) v[3 * k + i] = (float)rand_below(rng, 2 * res + 1) * 0.5f;
            v[3 * k + axis] = plane;
            s->idx[3 * t + k] = 3 * t + k;
        }
        if (t % 5 == 1) memcpy(v + 6, v + 3, 3 * sizeof(float));   /* a segment */
        if (t % 7 == 2) v[3 + (axis + 1) % 3] = v[(axis + 1) % 3];   /* edge along an axis */
    }
    for (k = 0; k < 9; k++) s->pos[k] = k < 3 ? 0 : (float)res;    /* triangle 0 spans the box */
}

/* A ray aimed at a point of a random triangle (a vertex, an edge, inside),
** from a random distance, sometimes axis-parallel, sometimes cut short. */
static void aimed_ray(uint64_t *rng, const soup *s, float size, brt_ray *ray)
{
    uint32_t t = rand_below(rng, s->tri_count);
    const float *v[3];
    float b1 = brt_random_float(rng), b2 = brt_random_float(rng), p[3], scale;
    int i, kind = (int)rand_below(rng, 8);
    if (b1 + b2 > 1) { b1 = 1 - b1; b2 = 1 - b2; }
    if (kind == 1) b1 = b2 = 0;                  /* a vertex */
    if (kind == 2) b2 = 0;                       /* an edge */
    for (i = 0; i < 3; i++) v[i] = s->pos + 3 * (size_t)s->idx[3 * (size_t)t + i];
    for (i = 0; i < 3; i++)
        p[i] = v[0][i] + b1 * (v[1][i] - v[0][i]) + b2 * (v[2][i] - v[0][i]);
    for (i = 0; i < 3; i++)
        ray->org[i] = p[i] + size * rand_range(rng, -3, 3) * (kind == 0 ? 0.001f : 1);
    if (kind == 3) {                              /* axis-parallel */
        int axis = (int)rand_below(rng, 3);
        for (i = 0; i < 3; i++) if (i != axis) ray->org[i] = p[i];
    }
    scale = rand_range(rng, 0.1f, 10);
    for (i = 0; i < 3; i++) ray->dir[i] = (p[i] - ray->org[i]) * scale;
    ray->tnear = kind == 4 ? rand_range(rng, 0, 1) / scale : 0;
    ray->tfar = kind == 5 ? 1 / scale : INFINITY;
    if (kind == 6)      /* random direction from inside the bounds */
        for (i = 0; i < 3; i++) ray->dir[i] = rand_range(rng, -1, 1);
}

/* Closest hit by brute force over brt_intersect_triangle (small soups). */
static int brute_hit(const soup *s, const brt_ray *ray, float *t_best, uint32_t *prim)
{
    uint32_t t;
    int hit = 0;
    for (t = 0; t < s->tri_count; t++) {
        float tt, u, v;
        const uint32_t *x = s->idx + 3 * (size_t)t;
        if (brt_intersect_triangle(ray, s->pos + 3 * (size_t)x[0], s->pos + 3 * (size_t)x[1],
                                   s->pos + 3 * (size_t)x[2], &tt, &u, &v) &&
            (!hit || tt < *t_best)) {
            *t_best = tt;
            *prim = t;
            hit = 1;
        }
    }
    return hit;
}

/* For failure messages: a triangle with zero area (edge cross product 0,
** exact in double for the lattice soups) must never report a hit. */
static int zero_area(const soup *s, uint32_t prim)
{
    const uint32_t *x = s->idx + 3 * (size_t)prim;
    double e[2][3], c[3];
    int i;
    for (i = 0; i < 3; i++) {
        e[0][i] = (double)s->pos[3 * (size_t)x[1] + i] - s->pos[3 * (size_t)x[0] + i];
        e[1][i] = (double)s->pos[3 * (size_t)x[2] + i] - s->pos[3 * (size_t)x[0] + i];
    }
    c[0] = e[0][1] * e[1][2] - e[0][2] * e[1][1];
    c[1] = e[0][2] * e[1][0] - e[0][0] * e[1][2];
    c[2] = e[0][0] * e[1][1] - e[0][1] * e[1][0];
    return c[0] == 0 && c[1] == 0 && c[2] == 0;
}

/* Casts rays at the soup and its proxy; a triangle hit the proxy misses,
** or enters later than, fails.  exact_cell > 0 overrides the frame to
** origin bmin, that cell (adversarial soups on voxel faces). */
static void end_to_end(const char *label, const soup *s, uint32_t res, float exact_cell,
                       uint32_t rays, int use_bvh)
{
    brt_grid grid;
    brt_svdag *dag = NULL;
    brt_bvh *bvh = NULL;
    brt_proxy proxy;
    brt_error err;
    float bmin[3], bmax[3], size = 0;
    uint64_t rng = test_seed() ^ (res * 7919u + s->tri_count), hits = 0, proxy_hits = 0, fails = 0;
    uint32_t n;
    int i;
    mesh_bounds(s->pos, s->vertex_count, bmin, bmax);
    for (i = 0; i < 3; i++) size = fmaxf(size, bmax[i] - bmin[i]);
    CHECK(brt_grid_init(&grid, bmin, bmax, res) == BRT_OK, "%s: grid", label);
    if (exact_cell > 0) grid.cell = exact_cell;
    CHECK(brt_voxelize(&grid, s->pos, s->idx, s->tri_count) == BRT_OK, "%s: voxelize", label);
    CHECK(brt_svdag_create(&dag) == BRT_OK && brt_svdag_add(dag, &grid, &proxy) == BRT_OK,
          "%s: add", label);
    EXPECT(brt_svdag_check(dag, &err) == BRT_OK, "%s: %s", label, err.message);
    if (use_bvh && brt_bvh_build(s->pos, s->idx, s->tri_count, NULL, &bvh) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s: bvh build", label);
        rays = 0;
    }
    for (n = 0; n < rays; n++) {
        brt_ray ray;
        brt_hit hit;
        float t_entry, t_hit = 0;
        uint32_t prim = 0;
        int want, got;
        aimed_ray(&rng, s, size, &ray);
        if (use_bvh) {
            brt_hit_clear(&hit);
            brt_bvh_intersect(bvh, &ray, &hit);
            want = hit.prim != BRT_NO_PRIM;
            t_hit = hit.t;
            prim = hit.prim;
        } else {
            want = brute_hit(s, &ray, &t_hit, &prim);
        }
        got = brt_proxy_raycast(dag, &proxy, &ray, ray.tnear, ray.tfar, &t_entry);
        if (!check_reference_cast(dag, &proxy, &ray, got, t_entry, want, t_hit)) rays = n;
        hits += want;
        proxy_hits += got;
        if (want && !(got && t_entry <= t_hit)) {
            if (++fails <= 5)
                test_fail_at(__FILE__, __LINE__,
                             "%s: ray (%a %a %a) dir (%a %a %a) [%a %a] hits triangle %u at t %a, "
                             "proxy %d t %a%s",
                             label, ray.org[0], ray.org[1], ray.org[2], ray.dir[0], ray.dir[1],
                             ray.dir[2], ray.tnear, ray.tfar, prim, t_hit, got, t_entry,
                             zero_area(s, prim) ? " (a zero-area triangle reported a hit: a defect "
                                                  "of brt_intersect_triangle, not of the proxy)" : "");
        }
    }
    printf("  svdag: %-34s res %4u: %u rays, %llu hit triangles, %llu hit the proxy, %llu failures\n",
           label, res, rays, (unsigned long long)hits, (unsigned long long)proxy_hits,
           (unsigned long long)fails);
    brt_bvh_free(bvh);
    brt_svdag_free(dag);
    brt_grid_free(&grid);
}

static void test_end_to_end_shared(void)
{
    static const struct { const char *mesh; float scale, offset; uint32_t res, rays; } cases[] = {
        {"bunny_tiny.obj", 1, 0, 128, 1000000}, {"bunny_tiny.obj", 1e-3f, 7, 2, 100000},
        {"bunny_tiny.obj", 1e5f, -3e5f, 16, 200000}, {"bunny.obj.gz", 1e5f, 0, 512, 1000000},
        {"bunny.obj.gz", 1e-3f, 0, 4, 100000}, {"dragon.obj.gz", 1, 0, 256, 1000000}};
    size_t c;
    for (c = 0; c < sizeof cases / sizeof cases[0]; c++) {
        soup s;
        char label[128];
        if (!soup_load(cases[c].mesh, cases[c].scale, cases[c].offset, &s)) {
            test_skip("%s not available (or not loadable)", cases[c].mesh);
            continue;
        }
        snprintf(label, sizeof label, "%s x%g %+g", cases[c].mesh, cases[c].scale, cases[c].offset);
        end_to_end(label, &s, cases[c].res, 0, cases[c].rays, 1);
        soup_free(&s);
    }
}

static void test_end_to_end_adversarial(void)
{
    uint64_t rng = test_seed() + 3;
    uint32_t res;
    for (res = 2; res <= 64; res *= 4) {
        soup s;
        char label[64];
        soup_on_faces(&rng, res, 60, &s);
        snprintf(label, sizeof label, "triangles on voxel faces");
        end_to_end(label, &s, res, 1, 150000, 0);
        soup_free(&s);
    }
}

/* The same soups moved far from the origin and scaled to extremes. */
static void test_end_to_end_scales(void)
{
    static const float scales[] = {1e-3f, 1e5f}, offsets[] = {1e3f, -1e5f};
    uint64_t rng = test_seed() + 4;
    int c;
    for (c = 0; c < 4; c++) {
        soup s;
        uint32_t i, res = c & 1 ? 512 : 32;
        char label[64];
        soup_on_faces(&rng, 16, 60, &s);
        for (i = 0; i < 9 * s.tri_count; i++)
            s.pos[i] = s.pos[i] * scales[c >> 1] + offsets[c & 1] * scales[c >> 1];
        snprintf(label, sizeof label, "faces soup x%g %+g", scales[c >> 1], offsets[c & 1] * scales[c >> 1]);
        end_to_end(label, &s, res, 0, 100000, 0);
        soup_free(&s);
    }
}

/* ===================================================================== */
/* Dedup, blobs                                                          */
/* ===================================================================== */

/* The proxy grid of a soup: voxelized into a frame fitted to its bounds. */
static int soup_grid(const soup *s, uint32_t res, brt_grid *grid)
{
    float bmin[3], bmax[3];
    mesh_bounds(s->pos, s->vertex_count, bmin, bmax);
    return brt_grid_init(grid, bmin, bmax, res) == BRT_OK &&
           brt_voxelize(grid, s->pos, s->idx, s->tri_count) == BRT_OK;
}

static void test_dedup(void)
{
    brt_svdag *dag;
    brt_grid grid, again;
    brt_proxy a, b, c;
    brt_error err;
    soup s;
    uint64_t rng = test_seed() + 5;
    uint32_t before, x, y, z;
    CHECK(brt_svdag_create(&dag) == BRT_OK, "create");
    soup_on_faces(&rng, 64, 200, &s);
    CHECK(soup_grid(&s, 64, &grid) && soup_grid(&s, 64, &again), "voxelize");
    soup_free(&s);
    CHECK(brt_svdag_add(dag, &grid, &a) == BRT_OK, "add a");
    CHECK(brt_svdag_check(dag, &err) == BRT_OK, "%s", err.message);
    before = brt_svdag_node_count(dag);
    CHECK(brt_svdag_add(dag, &again, &b) == BRT_OK, "add b");
    CHECK(brt_svdag_check(dag, &err) == BRT_OK, "%s", err.message);
    EXPECT(a.root == b.root && brt_svdag_node_count(dag) == before,
           "identical meshes: roots %u %u, nodes %u -> %u", a.root, b.root, before,
           brt_svdag_node_count(dag));
    do {   /* one voxel that is not set yet */
        x = rand_below(&rng, 64); y = rand_below(&rng, 64); z = rand_below(&rng, 64);
    } while (brt_grid_get(&grid, x, y, z));
    brt_grid_set(&grid, x, y, z);
    CHECK(brt_svdag_add(dag, &grid, &c) == BRT_OK, "add c");
    CHECK(brt_svdag_check(dag, &err) == BRT_OK, "%s", err.message);
    /* A 64^3 tree has 5 levels of nodes (4 interior + the leaf) on a path. */
    EXPECT(c.root != a.root && brt_svdag_node_count(dag) <= before + 5,
           "one voxel more: nodes %u -> %u", before, brt_svdag_node_count(dag));
    brt_grid_free(&grid);
    brt_grid_free(&again);
    brt_svdag_free(dag);
}

/* A pool of a few proxies, its blob, and the proxies. */
static brt_svdag *small_pool(brt_proxy proxies[3], uint64_t *rng)
{
    brt_svdag *dag;
    uint32_t res[3] = {2, 16, 32};
    float origin[3] = {0, 0, 0};
    int i;
    if (brt_svdag_create(&dag) != BRT_OK) return NULL;
    for (i = 0; i < 3; i++) {
        brt_grid grid;
        grid_exact(&grid, res[i], origin, 1);
        fill_random(&grid, rng);
        brt_svdag_add(dag, &grid, &proxies[i]);
        brt_grid_free(&grid);
    }
    return dag;
}

static void test_blob_round_trip(void)
{
    brt_proxy proxies[3];
    uint64_t rng = test_seed() + 6;
    brt_svdag *dag = small_pool(proxies, &rng), *back = NULL;
    brt_error err;
    unsigned char *blob;
    size_t size;
    int i, n;
    CHECK(dag, "pool");
    size = brt_svdag_blob_size(dag);
    blob = (unsigned char *)malloc(size);
    brt_svdag_blob_write(dag, blob);
    CHECK(brt_svdag_blob_open(blob, size, &back, &err) == BRT_OK, "open: %s", err.message);
    EXPECT(brt_svdag_node_count(back) == brt_svdag_node_count(dag), "node count");
    for (i = 0; i < 3; i++) {
        brt_grid g1, g2;
        size_t words = ((size_t)proxies[i].res * proxies[i].res * proxies[i].res + 63) / 64;
        EXPECT(brt_svdag_decode(dag, &proxies[i], &g1) == BRT_OK &&
                   brt_svdag_decode(back, &proxies[i], &g2) == BRT_OK &&
                   memcmp(g1.bits, g2.bits, words * 8) == 0,
               "proxy %d decodes differently", i);
        for (n = 0; n < 500; n++) {
            brt_ray ray;
            float t1, t2;
            int h1, h2;
            lattice_ray(&rng, &g1, &ray);
            h1 = brt_proxy_raycast(dag, &proxies[i], &ray, ray.tnear, ray.tfar, &t1);
            h2 = brt_proxy_raycast(back, &proxies[i], &ray, ray.tnear, ray.tfar, &t2);
            EXPECT(h1 == h2 && (!h1 || t1 == t2), "proxy %d casts differently", i);
        }
        brt_grid_free(&g1);
        brt_grid_free(&g2);
    }
    {   /* an opened pool accepts more proxies and dedups against the old ones */
        brt_grid grid;
        brt_proxy again;
        uint32_t nodes = brt_svdag_node_count(back);
        EXPECT(brt_svdag_decode(dag, &proxies[2], &grid) == BRT_OK &&
                   brt_svdag_add(back, &grid, &again) == BRT_OK && again.root == proxies[2].root &&
                   brt_svdag_node_count(back) == nodes && brt_svdag_check(back, &err) == BRT_OK,
               "re-adding a proxy to an opened pool");
        brt_grid_free(&grid);
    }
    free(blob);
    brt_svdag_free(back);
    brt_svdag_free(dag);
}

/* Opens a damaged blob: a format error, or a pool that passes its check
** and whose casts, whatever the proxies point at now, answer as a fresh
** pool built from the grids they decode to (the cast depends only on the
** voxels).  A proxy that no longer fits the pool fails brt_proxy_check
** and is not cast: the cast's contract is checked proxies only. */
static void try_corrupt(const unsigned char *blob, size_t size, const brt_proxy proxies[3],
                        uint64_t *rng, uint32_t *opened)
{
    brt_svdag *back = NULL;
    brt_error err;
    brt_result r = brt_svdag_blob_open(blob, size, &back, &err);
    int i, n;
    EXPECT(r == BRT_OK || r == BRT_EFORMAT, "corrupt blob gave %s", brt_result_string(r));
    if (r != BRT_OK) {
        EXPECT(back == NULL && err.message[0], "no message or a pool left");
        return;
    }
    ++*opened;
    EXPECT(brt_svdag_check(back, &err) == BRT_OK, "opened a pool that fails its check");
    for (i = 0; i < 3 && !test_failed(); i++) {
        brt_grid grid;
        brt_svdag *fresh = NULL;
        brt_proxy again;
        /* the cast's contract: only proxies that pass their check */
        int valid = brt_proxy_check(back, &proxies[i], NULL) == BRT_OK;
        int decoded = valid && brt_svdag_decode(back, &proxies[i], &grid) == BRT_OK;
        EXPECT(!valid || decoded, "proxy %d of a damaged pool passes its check but does not decode", i);
        if (decoded) {
            CHECK(brt_svdag_create(&fresh) == BRT_OK && brt_svdag_add(fresh, &grid, &again) == BRT_OK,
                  "rebuilding a decoded proxy");
            brt_grid_free(&grid);
        }
        for (n = 0; n < 20 && decoded; n++) {
            brt_ray ray;
            float t = -1, t_fresh = -1;
            int got, want;
            memcpy(grid.origin, proxies[i].origin, sizeof grid.origin);
            grid.cell = proxies[i].cell;
            grid.res = proxies[i].res;
            lattice_ray(rng, &grid, &ray);
            got = brt_proxy_raycast(back, &proxies[i], &ray, ray.tnear, ray.tfar, &t);
            want = brt_proxy_raycast(fresh, &again, &ray, ray.tnear, ray.tfar, &t_fresh);
            EXPECT(got == want && (!got || t == t_fresh),
                   "proxy %d of a damaged pool: cast %d t %a, expected %d t %a", i, got, t, want,
                   t_fresh);
        }
        brt_svdag_free(fresh);
    }
    brt_svdag_free(back);
}

static void test_blob_corrupt(void)
{
    brt_proxy proxies[3];
    uint64_t rng = test_seed() + 7;
    brt_svdag *dag = small_pool(proxies, &rng);
    unsigned char *blob, *copy;
    size_t size, cut, n;
    uint32_t opened = 0;
    CHECK(dag, "pool");
    size = brt_svdag_blob_size(dag);
    blob = (unsigned char *)malloc(size);
    copy = (unsigned char *)malloc(size);
    brt_svdag_blob_write(dag, blob);
    for (cut = 0; cut < size && !test_failed(); cut += 1 + cut / 64)   /* truncations */
        try_corrupt(blob, cut, proxies, &rng, &opened);
    EXPECT(opened == 0, "a truncated blob opened");
    for (n = 0; n < 3000 && !test_failed(); n++) {    /* byte and bit flips */
        size_t k, flips = 1 + rand_below(&rng, 3);
        memcpy(copy, blob, size);
        for (k = 0; k < flips; k++) {
            size_t at = rand_below(&rng, (uint32_t)size);
            copy[at] ^= rand_below(&rng, 2) ? (unsigned char)(1u << rand_below(&rng, 8))
                                            : (unsigned char)rand_below(&rng, 256);
        }
        try_corrupt(copy, size, proxies, &rng, &opened);
    }
    {   /* a duplicated leaf: the dedup invariant is checked too */
        unsigned char dup[24 + 16];
        brt_svdag *none = NULL;
        memcpy(dup, blob, 24);
        dup[12] = dup[13] = dup[14] = dup[15] = 0;            /* no words */
        dup[16] = 2; dup[17] = dup[18] = dup[19] = 0;         /* two leaves */
        memset(dup + 24, 0x11, 16);
        EXPECT(brt_svdag_blob_open(dup, sizeof dup, &none, NULL) == BRT_EFORMAT && !none,
               "duplicate leaves accepted");
    }
    {   /* an empty leaf (the smallest pool: no words, one leaf of 0) */
        unsigned char empty[24 + 8];
        brt_svdag *none = NULL;
        memcpy(empty, blob, 24);
        empty[12] = empty[13] = empty[14] = empty[15] = 0;        /* no words */
        empty[16] = 1; empty[17] = empty[18] = empty[19] = 0;     /* one leaf */
        memset(empty + 24, 0, 8);
        EXPECT(brt_svdag_blob_open(empty, sizeof empty, &none, NULL) == BRT_EFORMAT && !none,
               "an empty leaf accepted");
    }
    {   /* a node whose child is itself (one leaf, a two-word node) */
        unsigned char loop[24 + 8 + 8];
        const uint32_t node[2] = {0x01u, 0u};   /* child 0 present, at word 0 */
        brt_svdag *none = NULL;
        memcpy(loop, blob, 24);
        loop[12] = 2; loop[13] = loop[14] = loop[15] = 0;         /* two words */
        loop[16] = 1; loop[17] = loop[18] = loop[19] = 0;         /* one leaf */
        memset(loop + 24, 0x11, 8);
        memcpy(loop + 32, node, 8);
        EXPECT(brt_svdag_blob_open(loop, sizeof loop, &none, NULL) == BRT_EFORMAT && !none,
               "a node that is its own child accepted");
        brt_svdag_free(none);
    }
    printf("  svdag: corrupt blobs: %u of the flipped ones still valid pools\n", opened);
    free(copy);
    free(blob);
    brt_svdag_free(dag);
}

/* ===================================================================== */
/* build/voxelize                                                        */
/* ===================================================================== */

/* Runs a shell command line; its exit status (-1 when it did not run). */
static int run_status(const char *command)
{
    int status = system(command);
    return status != -1 && WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

static char *read_text(const char *path)
{
    FILE *f = fopen(path, "rb");
    char *text;
    long n;
    if (!f) return NULL;
    fseek(f, 0, SEEK_END);
    n = ftell(f);
    rewind(f);
    text = (char *)calloc((size_t)n + 1, 1);
    if (text && fread(text, 1, (size_t)n, f) != (size_t)n) { free(text); text = NULL; }
    fclose(f);
    return text;
}

static void test_voxelize_program(void)
{
    static const char obj[] = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 2 3 4\n";
    static const float pos[12] = {0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1};
    static const uint32_t idx[9] = {0, 1, 2, 0, 1, 3, 1, 2, 3};
    const char *build = getenv("BRT_BUILD") ? getenv("BRT_BUILD") : "build", *dir = test_tmpdir();
    char cmd[2048], path[512];
    char *json, *err;
    float bmin[3] = {0, 0, 0}, bmax[3] = {1, 1, 1};
    brt_grid grid;
    FILE *f;
    snprintf(path, sizeof path, "%s/svdag_tet.obj", dir);
    f = fopen(path, "wb");
    CHECK(f && fwrite(obj, 1, sizeof obj - 1, f) == sizeof obj - 1 && fclose(f) == 0, "write %s", path);
    snprintf(cmd, sizeof cmd, "%s/voxelize %s --proxy-res 16 --stats %s/svdag_s.json --out %s/svdag_p.png "
             "--size 32 > %s/svdag_out.txt 2>&1", build, path, dir, dir, dir);
    if (run_status(cmd) != 0) {
        test_skip("%s/voxelize did not run (not built?)", build);
        return;
    }
    snprintf(path, sizeof path, "%s/svdag_s.json", dir);
    json = read_text(path);
    CHECK(brt_grid_init(&grid, bmin, bmax, 16) == BRT_OK && brt_voxelize(&grid, pos, idx, 3) == BRT_OK,
          "library voxelize");
    EXPECT(tu_json_number(json, "triangles") == 3 && tu_json_number(json, "resolution") == 16 &&
               tu_json_number(json, "voxels") == (double)brt_grid_count(&grid) &&
               tu_json_number(json, "svo_nodes") > 0 && tu_json_number(json, "dag_nodes") > 0 &&
               tu_json_number(json, "dag_bytes") > 0 && json && strstr(json, "\"seconds\":"),
           "stats JSON: %s", json ? json : "(missing)");
    free(json);
    brt_grid_free(&grid);
    snprintf(path, sizeof path, "%s/svdag_p.png", dir);
    json = read_text(path);
    EXPECT(json && memcmp(json, "\x89PNG", 4) == 0, "no PNG written");
    free(json);
    /* Bad input: exit 1, one line "voxelize: file:line: reason", no output. */
    snprintf(path, sizeof path, "%s/svdag_bad.obj", dir);
    f = fopen(path, "wb");
    CHECK(f && fputs("v 0 0 0\nv 1 0 0\nf 1 2 7\n", f) >= 0 && fclose(f) == 0, "write %s", path);
    snprintf(cmd, sizeof cmd, "%s/voxelize %s --stats %s/svdag_bad.json --out %s/svdag_bad.png "
             "2> %s/svdag_err.txt", build, path, dir, dir, dir);
    EXPECT(run_status(cmd) == 1, "bad mesh: exit status not 1");
    snprintf(path, sizeof path, "%s/svdag_err.txt", dir);
    err = read_text(path);
    EXPECT(err && strncmp(err, "voxelize: ", 10) == 0 && strstr(err, "svdag_bad.obj:3") &&
               strchr(err, '\n') == err + strlen(err) - 1,
           "bad mesh: stderr '%s'", err ? err : "(none)");
    free(err);
    snprintf(path, sizeof path, "%s/svdag_bad.json", dir);
    f = fopen(path, "rb");
    EXPECT(f == NULL, "bad mesh: stats written");
    if (f) fclose(f);
    snprintf(cmd, sizeof cmd, "%s/voxelize %s/svdag_tet.obj --proxy-res 24 2>/dev/null >/dev/null", build, dir);
    EXPECT(run_status(cmd) == 1, "--proxy-res 24 accepted");
}

/* ===================================================================== */
/* Grazing directions and float edge values (issue 32, classes 1 and 9)   */
/* ===================================================================== */

/*
** Rays parallel and nearly parallel to the grid's axes and planes, from
** far outside the box, at triangles lying in and near axis planes, against
** two independent references: the brute-force triangle test (a triangle
** the segment hits must lie in a voxel that both casts report, entered no
** later) and exact slabs over the set voxels (every closed voxel box the
** segment touches is reported; every box grown by the g that svdag.c
** states, too).  Direction components: +-0, subnormals, 2^-40 (the cast's
** tilt threshold) and values either side of it; coordinates on the
** triangles' planes and edges, on voxel planes, one float either side.
*/

/* The set voxels of a grid, listed once for oracles over many rays. */
typedef struct voxel_list {
    uint32_t (*at)[3];
    size_t count;
} voxel_list;

static void voxel_list_of(const brt_grid *grid, voxel_list *list)
{
    uint32_t x, y, z;
    list->count = 0;
    list->at = malloc((size_t)brt_grid_count(grid) * sizeof *list->at + 1);
    if (!list->at) return;
    for (z = 0; z < grid->res; z++)
        for (y = 0; y < grid->res; y++)
            for (x = 0; x < grid->res; x++)
                if (brt_grid_get(grid, x, y, z)) {
                    list->at[list->count][0] = x;
                    list->at[list->count][1] = y;
                    list->at[list->count++][2] = z;
                }
}

/* oracle_grid over a list of the set voxels. */
static int oracle_list(const brt_grid *grid, const voxel_list *list, const brt_ray *ray,
                       double grow, double *t_best)
{
    size_t i;
    int hit = 0;
    for (i = 0; i < list->count; i++) {
        double t;
        if (oracle_voxel(grid, list->at[i], ray, grow, &t) && (!hit || t < *t_best)) {
            *t_best = t;
            hit = 1;
        }
    }
    return hit;
}

/* Direction components of grazing rays: signed zeros, subnormals, the
** cast's tilt threshold 2^-40 (relative to the main component 1) and
** values on either side of it, and small normal ones. */
static const float grazing_components[] = {
    0.0f, -0.0f, 0x1p-149f, -0x1p-149f, 1e-40f, -1e-40f, 0x1p-126f, 1e-20f, -1e-20f,
    0x1p-41f, 0x1p-40f, -0x1p-40f, 0x1p-39f, 1e-7f, -1e-7f, 0x1p-20f, -0x1p-16f};

/* A coordinate on axis a of a grazing ray's origin: that of the point p
** on a triangle (aimed, or by chance), a plane of the box or of a voxel,
** one float either side of it, -0 for 0, or anywhere near. */
static float grazing_coordinate(uint64_t *rng, const brt_grid *grid, const float lo[3],
                                const float hi[3], const float p[3], int aimed, int a)
{
    float v;
    switch (aimed ? 4 : rand_below(rng, 6)) {
    case 0: v = lo[a]; break;
    case 1: v = hi[a]; break;
    case 2: v = grid->origin[a] + grid->cell * (float)rand_below(rng, grid->res + 1); break;
    case 3: v = rand_range(rng, lo[a] - grid->cell, hi[a] + grid->cell); break;
    default: v = p[a]; break;
    }
    switch (rand_below(rng, 4)) {
    case 0: return nextafterf(v, INFINITY);
    case 1: return nextafterf(v, -INFINITY);
    default: return v == 0 && rand_below(rng, 2) ? -0.0f : v;
    }
}

/* A ray along axis a (either sign), from far outside [lo, hi] (1000, 10^6
** or a small distance, in units of the box), its other components from
** grazing_components, aimed at a vertex, an edge or the inside of a
** triangle of s or near it; segment [0, inf] unless the caller cuts it. */
static void grazing_ray(uint64_t *rng, const soup *s, const brt_grid *grid, const float lo[3],
                        const float hi[3], brt_ray *ray)
{
    static const float distances[] = {1000, 1e6f, 2, 0.5f};
    const size_t nc = sizeof grazing_components / sizeof grazing_components[0];
    const float *v = s->pos + 9 * (size_t)rand_below(rng, s->tri_count);
    float b1 = brt_random_float(rng), b2 = brt_random_float(rng), p[3];
    float sign = rand_below(rng, 2) ? 1.0f : -1.0f, far = distances[rand_below(rng, 4)];
    int a = (int)rand_below(rng, 3), aimed = (int)rand_below(rng, 2), i;
    if (b1 + b2 > 1) { b1 = 1 - b1; b2 = 1 - b2; }
    if (rand_below(rng, 3) == 0) b2 = 0;                   /* an edge */
    if (rand_below(rng, 4) == 0) b1 = b2 = 0;              /* a vertex */
    for (i = 0; i < 3; i++) p[i] = v[i] + b1 * (v[3 + i] - v[i]) + b2 * (v[6 + i] - v[i]);
    for (i = 0; i < 3; i++) {
        ray->org[i] = grazing_coordinate(rng, grid, lo, hi, p, aimed, i);
        ray->dir[i] = grazing_components[rand_below(rng, (uint32_t)nc)];
    }
    ray->org[a] = sign > 0 ? lo[a] - far : hi[a] + far;
    ray->dir[a] = sign * (rand_below(rng, 2) ? 1.0f : 0.375f);
    ray->tnear = 0;
    ray->tfar = INFINITY;
}

/* Cuts the segment around the triangles' hit at t: a segment of one point
** [t, t], one ending at t, one starting before it; or leaves [0, inf]. */
static void grazing_segment(uint64_t *rng, const soup *s, brt_ray *ray)
{
    float t;
    uint32_t prim;
    unsigned kind = rand_below(rng, 8);
    if (kind > 2 || !brute_hit(s, ray, &t, &prim)) return;
    if (kind == 0) ray->tnear = t;
    if (kind == 2) ray->tnear = t * rand_range(rng, 0, 1);
    if (kind <= 1) ray->tfar = t;
}

/* The triangle test's verdict for the cast's answer (got, t_entry): a hit
** must be reported, entered no later; 0 after reporting a failure. */
static int grazing_check_triangles(const soup *s, const brt_ray *ray, int got, float t_entry,
                                   uint32_t res, const char *label)
{
    float t_hit = 0;
    uint32_t prim = 0;
    if (!brute_hit(s, ray, &t_hit, &prim) || (got && t_entry <= t_hit)) return 1;
    test_fail_at(__FILE__, __LINE__, "%s res %u: ray (%a %a %a) dir (%a %a %a) [%a %a] hits "
                 "triangle %u at t %a, proxy %d t %a", label, res, ray->org[0], ray->org[1],
                 ray->org[2], ray->dir[0], ray->dir[1], ray->dir[2], ray->tnear, ray->tfar, prim,
                 t_hit, got, t_entry);
    return 0;
}

/* The exact slabs' verdict: every set voxel's closed box, and every one
** grown by the stated g (less 2^-20 of it, as in the ray-cast oracle
** test), that the segment touches is reported, entered no later. */
static int grazing_check_voxels(const brt_grid *grid, const voxel_list *list,
                                const brt_proxy *proxy, const brt_ray *ray, int got,
                                float t_entry, const char *label)
{
    double t_exact = 0, t_stated = 0;
    int exact = oracle_list(grid, list, ray, 0, &t_exact);
    int stated = oracle_list(grid, list, ray, stated_grow(proxy, ray) * (1 - 0x1p-20), &t_stated);
    if ((!exact || (got && t_entry <= t_exact)) && (!stated || (got && t_entry <= t_stated)))
        return 1;
    test_fail_at(__FILE__, __LINE__, "%s res %u: ray (%a %a %a) dir (%a %a %a) [%a %a]: voxel "
                 "touched %d at t %a, grown by the stated g %d at t %a; proxy %d t %a", label,
                 grid->res, ray->org[0], ray->org[1], ray->org[2], ray->dir[0], ray->dir[1],
                 ray->dir[2], ray->tnear, ray->tfar, exact, t_exact, stated, t_stated, got, t_entry);
    return 0;
}

/* The same ray with the sign of every zero flipped (origin, direction,
** tnear): 1 when there was one.  It is the same segment, so the triangle
** test and the cast must answer alike. */
static int signed_zero_twin(const brt_ray *ray, brt_ray *twin)
{
    int i, any = 0;
    *twin = *ray;
    for (i = 0; i < 3; i++) {
        if (ray->org[i] == 0) { twin->org[i] = signbit(ray->org[i]) ? 0.0f : -0.0f; any = 1; }
        if (ray->dir[i] == 0) { twin->dir[i] = signbit(ray->dir[i]) ? 0.0f : -0.0f; any = 1; }
    }
    if (ray->tnear == 0) { twin->tnear = signbit(ray->tnear) ? 0.0f : -0.0f; any = 1; }
    return any;
}

/* Signed zeros (issue 32, class 9): the twin gets the same triangle hit
** (t and triangle; u and v may differ in the sign of a zero) and the same
** cast answer and entry as the ray (got, t_entry). */
static void check_signed_zeros(const soup *s, const brt_svdag *dag, const brt_proxy *proxy,
                               const brt_ray *ray, int got, float t_entry, const char *label)
{
    brt_ray twin;
    float t1 = 0, t2 = 0, e2 = 0;
    uint32_t p1 = 0, p2 = 0;
    int h1, h2, g2;
    if (!signed_zero_twin(ray, &twin)) return;
    h1 = brute_hit(s, ray, &t1, &p1);
    h2 = brute_hit(s, &twin, &t2, &p2);
    g2 = brt_proxy_raycast(dag, proxy, &twin, twin.tnear, twin.tfar, &e2);
    EXPECT(h1 == h2 && (!h1 || (t1 == t2 && p1 == p2)) && got == g2 && (!got || t_entry == e2),
           "%s res %u: ray (%a %a %a) dir (%a %a %a) [%a %a] and its signed-zero twin differ: "
           "triangles %d t %a (%u) / %d t %a (%u), proxy %d t %a / %d t %a", label, proxy->res,
           ray->org[0], ray->org[1], ray->org[2], ray->dir[0], ray->dir[1], ray->dir[2], ray->tnear,
           ray->tfar, h1, t1, p1, h2, t2, p2, got, t_entry, g2, e2);
}

/* Triangles in and near axis planes (9 floats each). */
typedef struct grazing_case {
    const char *label;
    uint32_t tri_count;
    float tri[3][9];
} grazing_case;

static const grazing_case grazing_cases[] = {
    {"in x = 0", 1, {{0, 0, 0, 0, 1, 0, 0, 0, 1}}},
    {"a corner, one per axis plane", 3,
     {{0, 0, 0, 0, 1, 0, 0, 0, 1}, {0, 0, 0, 1, 0, 0, 0, 0, 1}, {0, 0, 0, 1, 0, 0, 0, 1, 0}}},
    {"near x = 0 (tilted by 2^-20)", 1, {{0, 0, 0, 0x1p-20f, 1, 0, 0, 0, 1}}},
    {"in x = 0, signed zeros", 1, {{-0.0f, 0, 0, -0.0f, 1, -0.0f, 0, -0.0f, 1}}},
    {"in y = 5, far from the origin", 2,
     {{-3, 5, 1000, 4, 5, 1000, -3, 5, 1007}, {4, 5, 1000, 4, 5, 1007, -3, 5, 1007}}}};

/* A soup of the case's triangles (3 corners each, not shared). */
static void soup_of_case(const grazing_case *c, soup *s)
{
    uint32_t k;
    s->tri_count = c->tri_count;
    s->vertex_count = 3 * c->tri_count;
    s->pos = malloc(9 * (size_t)c->tri_count * sizeof *s->pos);
    s->idx = malloc(3 * (size_t)c->tri_count * sizeof *s->idx);
    if (!s->pos || !s->idx) { soup_free(s); return; }
    for (k = 0; k < 3 * c->tri_count; k++) s->idx[k] = k;
    for (k = 0; k < c->tri_count; k++) memcpy(s->pos + 9 * (size_t)k, c->tri[k], 9 * sizeof(float));
}

/* One case at one resolution: its proxy, in a grid fitted to its box as
** the scene build fits it, cast with rays grazing_ray makes. */
static void grazing_run(const grazing_case *c, uint32_t res, uint32_t rays, uint64_t *rng,
                        uint64_t *hits)
{
    brt_grid grid;
    brt_svdag *dag = NULL;
    brt_proxy proxy;
    voxel_list list = {NULL, 0};
    soup s = {NULL, NULL, 0, 0};
    float lo[3], hi[3];
    uint32_t n;
    soup_of_case(c, &s);
    CHECK(s.pos && brt_svdag_create(&dag) == BRT_OK, "%s: out of memory", c->label);
    mesh_bounds(s.pos, s.vertex_count, lo, hi);
    if (brt_grid_init(&grid, lo, hi, res) != BRT_OK ||
        brt_voxelize(&grid, s.pos, s.idx, s.tri_count) != BRT_OK ||
        brt_svdag_add(dag, &grid, &proxy) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s res %u: proxy", c->label, res);
        rays = 0;
    } else {
        voxel_list_of(&grid, &list);
    }
    for (n = 0; n < rays && !test_failed(); n++) {
        brt_ray ray;
        float t_entry = 0, t_hit = 0;
        uint32_t prim;
        int got, want;
        grazing_ray(rng, &s, &grid, lo, hi, &ray);
        grazing_segment(rng, &s, &ray);
        want = brute_hit(&s, &ray, &t_hit, &prim);
        *hits += want;
        got = brt_proxy_raycast(dag, &proxy, &ray, ray.tnear, ray.tfar, &t_entry);
        if (!grazing_check_triangles(&s, &ray, got, t_entry, res, c->label) ||
            !check_reference_cast(dag, &proxy, &ray, got, t_entry, want, t_hit) ||
            !grazing_check_voxels(&grid, &list, &proxy, &ray, got, t_entry, c->label))
            break;
        EXPECT(brt_proxy_raycast(dag, &proxy, &ray, ray.tnear, ray.tfar, NULL) == got,
               "%s res %u: the yes/no cast disagrees", c->label, res);
        check_signed_zeros(&s, dag, &proxy, &ray, got, t_entry, c->label);
    }
    free(list.at);
    soup_free(&s);
    if (rays) brt_grid_free(&grid);
    brt_svdag_free(dag);
}

static void test_grazing_directions(void)
{
    static const uint32_t resolutions[] = {2, 4, 16, 128};
    uint64_t rng = test_seed() + 32, hits = 0;
    size_t c, r;
    for (c = 0; c < sizeof grazing_cases / sizeof grazing_cases[0]; c++)
        for (r = 0; r < 4 && !test_failed(); r++)
            grazing_run(&grazing_cases[c], resolutions[r], resolutions[r] == 128 ? 1500 : 3000,
                        &rng, &hits);
    /* the rays are aimed well enough to test something */
    EXPECT(hits > 10000, "only %llu rays hit a triangle", (unsigned long long)hits);
    printf("  svdag: grazing: %llu of the rays hit a triangle\n", (unsigned long long)hits);
}

/* The 12 triangles of the closed box [lo, hi] (9 floats each) into tri;
** zeros as -0 in every second triangle when negative_zeros (the same
** solid: a weld takes -0 = +0). */
static void closed_box(const float lo[3], const float hi[3], int negative_zeros, float tri[12][9])
{
    static const unsigned char quads[6][4] = {{0, 2, 6, 4}, {1, 5, 7, 3}, {0, 4, 5, 1},
                                              {2, 3, 7, 6}, {0, 1, 3, 2}, {4, 6, 7, 5}};
    static const unsigned char halves[2][3] = {{0, 1, 2}, {0, 2, 3}};
    int f, h, k, a;
    for (f = 0; f < 6; f++)
        for (h = 0; h < 2; h++)
            for (k = 0; k < 3; k++)
                for (a = 0; a < 3; a++) {
                    unsigned corner = quads[f][halves[h][k]];
                    float v = (corner >> a) & 1 ? hi[a] : lo[a];
                    tri[2 * f + h][3 * k + a] = v == 0 && negative_zeros && h ? -0.0f : v;
                }
}

/* The inner proxy of the 12 triangles tri at res, in a grid over [lo, hi]. */
static int inner_of_box(float tri[12][9], const float lo[3], const float hi[3], uint32_t res,
                        brt_svdag *dag, brt_proxy *proxy, brt_grid *grid)
{
    brt_solids *solids = NULL;
    int ok = brt_grid_init(grid, lo, hi, res) == BRT_OK;
    ok = ok && brt_solids_build(&tri[0][0], 9, 12, &solids) == BRT_OK &&
         brt_voxelize_inner(grid, solids) == BRT_OK && brt_svdag_add(dag, grid, proxy) == BRT_OK;
    brt_solids_free(solids);
    return ok;
}

/*
** Inner proxies at grazing directions: boxes near and far from the world
** origin, rays along the axes from far away (some past the cast's
** magnitude limit, which it must refuse) that graze the faces, edges and
** the voxel cores' planes.  An occluded verdict needs a triangle hit at t
** >= tnear by brute force; signed zeros do not change a verdict.
*/
static void test_grazing_inner(void)
{
    static const float boxes[2][2][3] = {{{0, 0, 0}, {1, 1, 1}}, {{500, 3, -2}, {501, 4.5f, -1}}};
    static const uint32_t resolutions[] = {8, 16, 32};
    uint64_t rng = test_seed() + 33, occluded = 0, rays = 0;
    size_t b, r;
    for (b = 0; b < 2; b++)
        for (r = 0; r < 3 && !test_failed(); r++) {
            float tri[12][9];
            soup s = {NULL, NULL, 36, 12};
            uint32_t idx[36], k, n;
            brt_svdag *dag;
            brt_proxy proxy;
            brt_grid grid;
            closed_box(boxes[b][0], boxes[b][1], 0, tri);
            for (k = 0; k < 36; k++) idx[k] = k;
            s.pos = &tri[0][0];
            s.idx = idx;
            CHECK(brt_svdag_create(&dag) == BRT_OK, "create");
            if (!inner_of_box(tri, boxes[b][0], boxes[b][1], resolutions[r], dag, &proxy, &grid)) {
                brt_svdag_free(dag);
                CHECK(0, "box %u res %u: inner proxy", (unsigned)b, resolutions[r]);
            }
            for (n = 0; n < 4000 && !test_failed(); n++) {
                brt_ray ray, twin;
                float t;
                uint32_t prim;
                int occ;
                grazing_ray(&rng, &s, &grid, boxes[b][0], boxes[b][1], &ray);
                if (rand_below(&rng, 2))        /* through the inside, along the main axis */
                    for (k = 0; k < 3; k++)
                        if (fabsf(ray.dir[k]) < 0.25f)
                            ray.org[k] = rand_range(&rng, boxes[b][0][k], boxes[b][1][k]);
                if (rand_below(&rng, 4) == 0) ray.tnear = rand_range(&rng, 0, 2000);
                occ = brt_inner_occludes(dag, &proxy, &ray);
                occluded += occ;
                rays++;
                EXPECT(!occ || brute_hit(&s, &ray, &t, &prim),
                       "box %u res %u: ray (%a %a %a) dir (%a %a %a) [%a inf] called occluded, "
                       "no triangle hit", (unsigned)b, resolutions[r], ray.org[0], ray.org[1],
                       ray.org[2], ray.dir[0], ray.dir[1], ray.dir[2], ray.tnear);
                if (signed_zero_twin(&ray, &twin))
                    EXPECT(brt_inner_occludes(dag, &proxy, &twin) == occ,
                           "box %u res %u: the signed-zero twin of ray (%a %a %a) dir (%a %a %a) "
                           "differs", (unsigned)b, resolutions[r], ray.org[0], ray.org[1],
                           ray.org[2], ray.dir[0], ray.dir[1], ray.dir[2]);
            }
            brt_grid_free(&grid);
            brt_svdag_free(dag);
        }
    /* enough of the rays pass through an inner voxel's core to test something */
    EXPECT(occluded * 50 > rays, "only %llu of %llu rays occluded", (unsigned long long)occluded,
           (unsigned long long)rays);
    printf("  svdag: grazing inner: %llu of %llu rays occluded\n", (unsigned long long)occluded,
           (unsigned long long)rays);
}

/* Signed zeros in a weld (issue 32, class 9): a closed box whose corners
** at 0 are written -0 in half of its triangles is the same solid, with the
** same inner voxels, at every resolution. */
static void test_inner_signed_zeros(void)
{
    static const float lo[3] = {0, 0, 0}, hi[3] = {1, 2, 1};
    uint32_t res;
    for (res = 8; res <= 32; res *= 2) {
        float plain[12][9], signed_zeros[12][9];
        brt_svdag *dag;
        brt_proxy a, b;
        brt_grid ga, gb;
        closed_box(lo, hi, 0, plain);
        closed_box(lo, hi, 1, signed_zeros);
        CHECK(brt_svdag_create(&dag) == BRT_OK, "create");
        if (!inner_of_box(plain, lo, hi, res, dag, &a, &ga) ||
            !inner_of_box(signed_zeros, lo, hi, res, dag, &b, &gb)) {
            brt_svdag_free(dag);
            CHECK(0, "res %u: inner proxies", res);
        }
        EXPECT(brt_grid_count(&ga) > 0 && brt_grid_count(&ga) == brt_grid_count(&gb) &&
                   memcmp(ga.bits, gb.bits, ((size_t)res * res * res + 63) / 64 * 8) == 0,
               "res %u: inner voxels %llu with +0, %llu with -0 corners", res,
               (unsigned long long)brt_grid_count(&ga), (unsigned long long)brt_grid_count(&gb));
        brt_grid_free(&ga);
        brt_grid_free(&gb);
        brt_svdag_free(dag);
    }
}

/* ===================================================================== */
/* Instances: brt_voxelize_instance against exact models                  */
/* ===================================================================== */

/* Transforms that take the quarter-cell lattice to itself exactly (integer
** entries, lattice translations): sheared, mirrored, rotated by quarter
** turns, at once; so that a transformed lattice triangle is exact and the
** integer SAT (oracle_overlap) is the exact model of its voxels. */
static const int lattice_xforms[][12] = {
    {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0},                 /* identity */
    {-1, 0, 0, 32, 0, 1, 0, 0, 0, 0, 1, 0},               /* mirrored in x */
    {1, 1, 0, -8, 0, 1, 0, 2, 0, 0, 1, 0},                /* sheared x += y */
    {0, 0, 1, 0, 1, 0, 0, 0, 0, -1, 0, 32},               /* a rotation, mirrored */
    {1, 0, 1, -4, 0, -1, 1, 12, 1, 1, 0, -9},             /* sheared, det 2 */
};

/* A prototype of n lattice triangles (quarter cells) in a cluster, its
** BVH, and its triangles in place. */
static brt_bvh *lattice_prototype(uint64_t *rng, uint32_t n, int64_t (*tri)[3][3])
{
    float *pos = malloc(9 * (size_t)n * sizeof *pos);
    uint32_t *idx = malloc(3 * (size_t)n * sizeof *idx), t;
    brt_bvh *bvh = NULL;
    int k, i;
    if (pos && idx)
        for (t = 0; t < n; t++) {
            lattice_triangle(rng, 4, tri[t]);   /* a cluster of 4 cells */
            for (k = 0; k < 3; k++)
                for (i = 0; i < 3; i++) {
                    pos[9 * t + 3 * k + i] = 0.25f * (float)tri[t][k][i];
                    idx[3 * t + k] = 3 * t + k;
                }
        }
    if (!pos || !idx || brt_bvh_build(pos, idx, n, NULL, &bvh) != BRT_OK) bvh = NULL;
    free(pos);
    free(idx);
    return bvh;
}

/* The exact model of an instance: into model (cleared), every voxel the
** integer SAT finds a transformed triangle touching (only the voxels
** around its bounding box are asked). */
static void lattice_instance_model(brt_grid *model, int64_t (*tri)[3][3], uint32_t n, const int m[12])
{
    uint32_t t;
    int k, a;
    grid_clear(model);
    for (t = 0; t < n; t++) {
        int64_t w[3][3], lo[3], hi[3], x, y, z;
        for (k = 0; k < 3; k++)
            for (a = 0; a < 3; a++)
                w[k][a] = m[4 * a] * tri[t][k][0] + m[4 * a + 1] * tri[t][k][1] + m[4 * a + 2] * tri[t][k][2] +
                          4 * (int64_t)m[4 * a + 3];
        for (a = 0; a < 3; a++) {
            int64_t l = w[0][a] < w[1][a] ? w[0][a] : w[1][a], h = w[0][a] > w[1][a] ? w[0][a] : w[1][a];
            l = l < w[2][a] ? l : w[2][a];
            h = h > w[2][a] ? h : w[2][a];
            lo[a] = l / 4 - 2 > 0 ? l / 4 - 2 : 0;
            hi[a] = h / 4 + 1 < (int64_t)model->res - 1 ? h / 4 + 1 : (int64_t)model->res - 1;
        }
        for (z = lo[2]; z <= hi[2]; z++)
            for (y = lo[1]; y <= hi[1]; y++)
                for (x = lo[0]; x <= hi[0]; x++)
                    if (oracle_overlap(w, (uint32_t)x, (uint32_t)y, (uint32_t)z))
                        brt_grid_set(model, (uint32_t)x, (uint32_t)y, (uint32_t)z);
    }
}

/* 1 when every voxel set in a is set in b. */
static int grid_within(const brt_grid *a, const brt_grid *b)
{
    size_t i, words = ((size_t)a->res * a->res * a->res + 63) / 64;
    for (i = 0; i < words; i++)
        if (a->bits[i] & ~b->bits[i]) return 0;
    return 1;
}

/* Lattice prototypes under exact sheared, mirrored and rotated transforms,
** with triangles on voxel faces, edges and corners (grazing): both modes
** set every voxel the exact SAT marks, and the pruned one nothing the
** every-triangle one does not. */
static void test_instance_voxels_lattice(void)
{
    static const float origin[3] = {0, 0, 0};
    const uint32_t n = 24;
    uint64_t rng = test_seed() + 41, want = 0, got = 0, every = 0;
    int64_t (*tri)[3][3] = malloc(n * sizeof *tri);
    int round, x;
    CHECK(tri != NULL, "out of memory");
    for (round = 0; round < 60 && !test_failed(); round++) {
        brt_bvh *bvh = lattice_prototype(&rng, n, tri);
        brt_grid pruned, full, model;
        if (!bvh) break;
        grid_exact(&pruned, 32, origin, 1.0f);
        grid_exact(&full, 32, origin, 1.0f);
        grid_exact(&model, 32, origin, 1.0f);
        for (x = 0; x < (int)(sizeof lattice_xforms / sizeof lattice_xforms[0]) && !test_failed(); x++) {
            int m[12], i;
            float xform[12];
            memcpy(m, lattice_xforms[x], sizeof m);
            for (i = 3; i < 12; i += 4) m[i] += 4 * (round % 3);
            for (i = 0; i < 12; i++) xform[i] = (float)m[i];
            grid_clear(&pruned);
            grid_clear(&full);
            CHECK(brt_voxelize_instance(&pruned, bvh, xform, 0.0f, INSTANCE_VOXELS_PRUNED) == BRT_OK, "pruned");
            CHECK(brt_voxelize_instance(&full, bvh, xform, 0.0f, INSTANCE_VOXELS_EVERY_TRIANGLE) == BRT_OK,
                  "every triangle");
            lattice_instance_model(&model, tri, n, m);
            EXPECT(grid_within(&model, &pruned) && grid_within(&model, &full),
                   "round %d, transform (%d %d %d %d / %d %d %d %d / %d %d %d %d): a voxel of the exact model "
                   "is not set (pruned: %d, every triangle: %d)", round, m[0], m[1], m[2], m[3], m[4], m[5],
                   m[6], m[7], m[8], m[9], m[10], m[11], grid_within(&model, &pruned),
                   grid_within(&model, &full));
            EXPECT(grid_within(&pruned, &full), "transform %d: the pruned voxelization sets a voxel the "
                   "every-triangle one does not (%llu against %llu)", x,
                   (unsigned long long)brt_grid_count(&pruned), (unsigned long long)brt_grid_count(&full));
            want += brt_grid_count(&model);
            got += brt_grid_count(&pruned);
            every += brt_grid_count(&full);
        }
        brt_grid_free(&model);
        brt_grid_free(&pruned);
        brt_grid_free(&full);
        brt_bvh_free(bvh);
    }
    free(tri);
    EXPECT(round == 60, "prototype build failed");
    printf("  svdag: instances on the lattice: %llu voxels exact, %llu pruned, %llu every triangle\n",
           (unsigned long long)want, (unsigned long long)got, (unsigned long long)every);
}

/* m = rotation (a unit axis, an angle) * shear (x += sh y) * diag(s), a
** mirror when s has an odd count of negatives; t the translation. */
static void rotated_xform(uint64_t *rng, float m[12], const float t[3])
{
    double axis[3], len = 0, angle = 6.283185307179586 * brt_random_float(rng), r[9], a[9], c, sn, k;
    const double sh = rand_range(rng, -1.5f, 1.5f);
    double sc[3];
    int i, j;
    for (i = 0; i < 3; i++) {
        axis[i] = rand_range(rng, -1, 1);
        len += axis[i] * axis[i];
        sc[i] = rand_range(rng, 0.3f, 3.0f) * (rand_below(rng, 2) ? -1 : 1);
    }
    len = sqrt(len) + 1e-9;
    for (i = 0; i < 3; i++) axis[i] /= len;
    c = cos(angle); sn = sin(angle); k = 1 - c;
    r[0] = c + axis[0] * axis[0] * k; r[1] = axis[0] * axis[1] * k - axis[2] * sn; r[2] = axis[0] * axis[2] * k + axis[1] * sn;
    r[3] = axis[1] * axis[0] * k + axis[2] * sn; r[4] = c + axis[1] * axis[1] * k; r[5] = axis[1] * axis[2] * k - axis[0] * sn;
    r[6] = axis[2] * axis[0] * k - axis[1] * sn; r[7] = axis[2] * axis[1] * k + axis[0] * sn; r[8] = c + axis[2] * axis[2] * k;
    for (i = 0; i < 3; i++) {                      /* a = r * shear */
        a[3 * i] = r[3 * i];
        a[3 * i + 1] = r[3 * i] * sh + r[3 * i + 1];
        a[3 * i + 2] = r[3 * i + 2];
    }
    for (i = 0; i < 3; i++) {
        for (j = 0; j < 3; j++) m[4 * i + j] = (float)(a[3 * i + j] * sc[j]);
        m[4 * i + 3] = t[i];
    }
}

/* Every voxel whose closed box lies within tol voxels of the world point p
** (double) is set. */
static int voxels_near_point_set(const brt_grid *grid, const double p[3], double tol)
{
    double lo[3], hi[3];
    uint32_t x, y, z;
    int a;
    for (a = 0; a < 3; a++) {
        const double q = (p[a] - grid->origin[a]) / grid->cell;
        lo[a] = floor(q - tol) > 0 ? floor(q - tol) : 0;
        hi[a] = floor(q + tol) < grid->res - 1.0 ? floor(q + tol) : grid->res - 1.0;
    }
    for (z = (uint32_t)lo[2]; z <= (uint32_t)hi[2]; z++)
        for (y = (uint32_t)lo[1]; y <= (uint32_t)hi[1]; y++)
            for (x = (uint32_t)lo[0]; x <= (uint32_t)hi[0]; x++)
                if (!brt_grid_get(grid, x, y, z)) return 0;
    return 1;
}

/* Thin triangles (slivers, leaves) under random rotations, shears and
** mirrors at the batched mode's dilation, on grids of voxels larger than
** a leaf node and smaller: every voxel within 0.99 of the dilation (in
** voxels, INSTANCE_DILATION) of a point of a triangle (its corners, its
** edges' midpoints, random points; computed in double) is set -- the
** dilation is kept, and the rounding bound covers what is left -- and the
** pruned grid lies within the every-triangle one. */
static void test_instance_voxels_rotated(void)
{
    const uint32_t n = 200;
    const double near = 0.99 * INSTANCE_DILATION;
    uint64_t rng = test_seed() + 4141, points = 0;
    float *pos = malloc(9 * (size_t)n * sizeof *pos);
    uint32_t *idx = malloc(3 * (size_t)n * sizeof *idx), t;
    int round, k, i;
    CHECK(pos && idx, "out of memory");
    for (round = 0; round < 40 && !test_failed(); round++) {
        static const float lo[3] = {-8, -8, -8}, hi[3] = {8, 8, 8};
        /* res 4: a few triangles inside one voxel (centred in it); 8 and
        ** 32: leaf nodes within a voxel, and across several */
        const uint32_t res = round % 3 == 0 ? 4 : round % 3 == 1 ? 8 : 32, count = res == 4 ? 3 : n;
        const float spread = res == 4 ? 0.08f : 1.0f, edge = res == 4 ? 0.08f : 0.4f;
        float at[3];
        brt_bvh *bvh = NULL;
        brt_grid pruned, full;
        float m[12];
        for (i = 0; i < 3; i++) at[i] = res == 4 ? (rand_below(&rng, 2) ? 2.0f : -2.0f) : rand_range(&rng, -2, 2);
        for (t = 0; t < count; t++) {   /* leaves: a point, and two short thin edges from it */
            const float base[3] = {rand_range(&rng, -spread, spread), rand_range(&rng, -spread, spread),
                                   rand_range(&rng, -spread, spread)};
            const float thin = round % 2 ? 1e-4f : 0.05f * edge;
            for (k = 0; k < 3; k++)
                for (i = 0; i < 3; i++)
                    pos[9 * t + 3 * k + i] = base[i] + (k == 0 ? 0.0f : k == 1 ? rand_range(&rng, -edge, edge)
                                                                               : rand_range(&rng, -thin, thin));
            for (k = 0; k < 3; k++) idx[3 * t + k] = 3 * t + k;
        }
        CHECK(brt_bvh_build(pos, idx, count, NULL, &bvh) == BRT_OK, "bvh build");
        rotated_xform(&rng, m, at);
        CHECK(brt_grid_init(&pruned, lo, hi, res) == BRT_OK && brt_grid_init(&full, lo, hi, res) == BRT_OK, "grid");
        CHECK(brt_voxelize_instance(&pruned, bvh, m, INSTANCE_DILATION * pruned.cell, INSTANCE_VOXELS_PRUNED) == BRT_OK,
              "pruned");
        CHECK(brt_voxelize_instance(&full, bvh, m, INSTANCE_DILATION * full.cell, INSTANCE_VOXELS_EVERY_TRIANGLE) ==
                  BRT_OK, "every triangle");
        for (t = 0; t < count && !test_failed(); t++) {
            int s;
            for (s = 0; s < 12; s++) {
                static const double corners[6][3] = {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}, {0.5, 0.5, 0}, {0, 0.5, 0.5}, {0.5, 0, 0.5}};
                double b[3], p[3];
                int a;
                if (s < 6) memcpy(b, corners[s], sizeof b);
                else {
                    b[0] = brt_random_float(&rng);
                    b[1] = (1 - b[0]) * brt_random_float(&rng);
                    b[2] = 1 - b[0] - b[1];
                }
                for (a = 0; a < 3; a++) {
                    double o[3];
                    for (k = 0; k < 3; k++)
                        o[k] = b[0] * pos[9 * t + k] + b[1] * pos[9 * t + 3 + k] + b[2] * pos[9 * t + 6 + k];
                    p[a] = (double)m[4 * a] * o[0] + (double)m[4 * a + 1] * o[1] + (double)m[4 * a + 2] * o[2] +
                           m[4 * a + 3];
                }
                points++;
                EXPECT(voxels_near_point_set(&pruned, p, near) && voxels_near_point_set(&full, p, near),
                       "round %d: triangle %u: a voxel within the dilation of (%.17g %.17g %.17g) is not set "
                       "(pruned %d, every triangle %d)", round, (unsigned)t, p[0], p[1], p[2],
                       voxels_near_point_set(&pruned, p, near), voxels_near_point_set(&full, p, near));
            }
        }
        EXPECT(grid_within(&pruned, &full), "round %d: the pruned voxelization sets a voxel the every-triangle "
               "one does not (%llu against %llu)", round, (unsigned long long)brt_grid_count(&pruned),
               (unsigned long long)brt_grid_count(&full));
        brt_grid_free(&pruned);
        brt_grid_free(&full);
        brt_bvh_free(bvh);
    }
    free(pos);
    free(idx);
    printf("  svdag: instances rotated, sheared, mirrored: %llu points checked\n", (unsigned long long)points);
}

/* The build's cost follows the voxels touched (issue 41): a prototype of n
** triangles inside one voxel hands none to the triangle test when pruned
** (its root box is one voxel: marked at once), every one when every
** triangle is tested (the analysis); both set the same voxels. */
static void test_instance_voxels_work(void)
{
    static const float lo[3] = {-8, -8, -8}, hi[3] = {8, 8, 8};
    static const float at_one[12] = {1, 0, 0, 1, 0, 1, 0, 1, 0, 0, 1, 1};   /* into the voxel [0, 2)^3 */
    const uint32_t n = 120;
    uint64_t rng = test_seed() + 414141, tested[2];
    float *pos = malloc(9 * (size_t)n * sizeof *pos);
    uint32_t *idx = malloc(3 * (size_t)n * sizeof *idx), t;
    brt_grid grids[2];
    brt_bvh *bvh = NULL;
    int mode;
    CHECK(pos && idx, "out of memory");
    for (t = 0; t < 9 * n; t++) pos[t] = rand_range(&rng, -0.2f, 0.2f);
    for (t = 0; t < 3 * n; t++) idx[t] = t;
    CHECK(brt_bvh_build(pos, idx, n, NULL, &bvh) == BRT_OK, "bvh build");
    for (mode = 0; mode < 2; mode++) {
        CHECK(brt_grid_init(&grids[mode], lo, hi, 8) == BRT_OK, "grid");
        brt_test_count_instance_triangles(1);
        CHECK(brt_voxelize_instance(&grids[mode], bvh, at_one, INSTANCE_DILATION * grids[mode].cell,
                                    mode ? INSTANCE_VOXELS_EVERY_TRIANGLE : INSTANCE_VOXELS_PRUNED) == BRT_OK,
              "voxelize");
        tested[mode] = brt_test_instance_triangles();
        brt_test_count_instance_triangles(0);
    }
    EXPECT(tested[0] == 0 && tested[1] == n, "triangles tested: %llu pruned, %llu every triangle; want 0 and %u",
           (unsigned long long)tested[0], (unsigned long long)tested[1], (unsigned)n);
    EXPECT(brt_grid_count(&grids[0]) == 1 && grid_within(&grids[0], &grids[1]) && grid_within(&grids[1], &grids[0]),
           "voxels set: %llu pruned, %llu every triangle; want the same one",
           (unsigned long long)brt_grid_count(&grids[0]), (unsigned long long)brt_grid_count(&grids[1]));
    brt_grid_free(&grids[0]);
    brt_grid_free(&grids[1]);
    brt_bvh_free(bvh);
    free(pos);
    free(idx);
}

/* ===================================================================== */
/* Instances end to end: the proxy is entered no later than any hit       */
/* ===================================================================== */

/* A prototype of the entry test: its triangles in object space (9 floats
** each), its BVH and the BVH's box. */
typedef struct entry_proto {
    float *pos;
    uint32_t *idx;
    uint32_t count;
    brt_bvh *bvh;
    float lo[3], hi[3];
} entry_proto;

/* kind 0: lattice triangles in a cluster of 4 cells (corners, faces,
** slivers, degenerate ones; lattice_triangle); 1: leaves (a point and two
** short edges from it, thin or very thin); 2: random triangles, some
** large.  0 when out of memory or the BVH build fails. */
static int entry_proto_make(uint64_t *rng, int kind, entry_proto *p)
{
    const uint32_t n = kind == 0 ? 24 : kind == 1 ? 40 : 12;
    uint32_t t;
    int k, i;
    memset(p, 0, sizeof *p);
    p->pos = malloc(9 * (size_t)n * sizeof *p->pos);
    p->idx = malloc(3 * (size_t)n * sizeof *p->idx);
    if (!p->pos || !p->idx) return 0;
    p->count = n;
    for (t = 0; t < n; t++) {
        float *v = p->pos + 9 * (size_t)t;
        if (kind == 0) {
            int64_t q[3][3];
            lattice_triangle(rng, 4, q);
            for (k = 0; k < 3; k++)
                for (i = 0; i < 3; i++) v[3 * k + i] = 0.25f * (float)q[k][i];
        } else if (kind == 1) {
            const float thin = rand_below(rng, 2) ? 1e-4f : 0.02f;
            for (i = 0; i < 3; i++) {
                v[i] = rand_range(rng, -1, 1);
                v[3 + i] = v[i] + rand_range(rng, -0.4f, 0.4f);
                v[6 + i] = v[i] + rand_range(rng, -thin, thin);
            }
        } else {
            const float size = t % 3 ? 0.5f : 3.0f;
            for (i = 0; i < 3; i++) {
                v[i] = rand_range(rng, -2, 2);
                v[3 + i] = v[i] + rand_range(rng, -size, size);
                v[6 + i] = v[i] + rand_range(rng, -size, size);
            }
        }
        for (k = 0; k < 3; k++) p->idx[3 * t + k] = 3 * t + (uint32_t)k;
    }
    if (brt_bvh_build(p->pos, p->idx, n, NULL, &p->bvh) != BRT_OK) return 0;
    brt_bvh_bounds(p->bvh, p->lo, p->hi);
    return 1;
}

static void entry_proto_free(entry_proto *p)
{
    brt_bvh_free(p->bvh);
    free(p->pos);
    free(p->idx);
    memset(p, 0, sizeof *p);
}

/* The world point (double) of barycentric b on triangle t of a prototype
** under xform, and the triangle's world edges e1, e2 (double). */
static void entry_world_point(const entry_proto *p, uint32_t t, const float xform[12],
                             const double b[3], double w[3], double e1[3], double e2[3])
{
    const float *v = p->pos + 9 * (size_t)t;
    double c[3][3];
    int k, a;
    for (k = 0; k < 3; k++)
        for (a = 0; a < 3; a++)
            c[k][a] = (double)xform[4 * a] * v[3 * k] + (double)xform[4 * a + 1] * v[3 * k + 1] +
                      (double)xform[4 * a + 2] * v[3 * k + 2] + xform[4 * a + 3];
    for (a = 0; a < 3; a++) {
        w[a] = b[0] * c[0][a] + b[1] * c[1][a] + b[2] * c[2][a];
        e1[a] = c[1][a] - c[0][a];
        e2[a] = c[2][a] - c[0][a];
    }
}

/* The closest hit over every instance, brute force: each through
** brt_instance_intersect, the one function of every mode. */
static int entry_brute_hit(const entry_proto *protos, const brt_instance *inst,
                           const brt_instance_frame *frames, uint32_t count, const brt_ray *ray,
                           brt_hit *hit)
{
    uint32_t k;
    brt_hit_clear(hit);
    for (k = 0; k < count; k++)
        brt_instance_intersect(protos[inst[k].prototype].bvh, &frames[k], k, ray, hit, NULL);
    return hit->prim != BRT_NO_PRIM;
}

/* One ray at the instances, of one of eight kinds: random through the
** box; aimed at a vertex, an edge's midpoint, an edge or the inside of a
** world triangle from near or far; grazing (along an axis, the other
** components of the direction zero, subnormal or tiny, the origin on the
** point's coordinates or a float either side); a bounce (the origin on
** the triangle or a hair in front of or behind it, tnear 0 or tiny); along
** a direction in a triangle's plane (an edge's, or another), through a
** point of it.  Sometimes the segment is cut around the brute-force hit,
** as grazing_segment cuts it (the closest hit so far of a walk, tlimit). */
static void entry_ray(uint64_t *rng, const entry_proto *protos, const brt_instance *inst,
                      const brt_instance_frame *frames, uint32_t count, const float lo[3],
                      const float hi[3], float extent, brt_ray *ray)
{
    const size_t nc = sizeof grazing_components / sizeof grazing_components[0];
    const uint32_t k = rand_below(rng, count);
    const entry_proto *p = &protos[inst[k].prototype];
    const uint32_t t = rand_below(rng, p->count);
    const int kind = (int)rand_below(rng, 8), spot = (int)rand_below(rng, 4);
    double b[3], w[3], e1[3], e2[3], n[3], len;
    brt_hit hit;
    int a;
    b[0] = brt_random_float(rng);
    b[1] = (1 - b[0]) * brt_random_float(rng);
    if (spot == 0) { b[0] = rand_below(rng, 2); b[1] = b[0] ? 0 : rand_below(rng, 2); }   /* a vertex */
    if (spot == 1) { b[0] = 0.5; b[1] = rand_below(rng, 2) ? 0.5 : 0; }                   /* a midpoint */
    if (spot == 2) b[1] = 1 - b[0];                                                      /* an edge */
    b[2] = 1 - b[0] - b[1];
    entry_world_point(p, t, inst[k].xform, b, w, e1, e2);
    n[0] = e1[1] * e2[2] - e1[2] * e2[1];
    n[1] = e1[2] * e2[0] - e1[0] * e2[2];
    n[2] = e1[0] * e2[1] - e1[1] * e2[0];
    len = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    ray->tnear = 0;
    ray->tfar = INFINITY;
    switch (kind) {
    case 0:   /* random, from within the box grown by half */
        for (a = 0; a < 3; a++) {
            ray->org[a] = rand_range(rng, lo[a] - 0.5f * extent, hi[a] + 0.5f * extent);
            ray->dir[a] = rand_range(rng, -1, 1);
        }
        break;
    case 1:
    case 2: { /* aimed, from near (a thousandth of the box) or from about it */
        const float from = kind == 1 ? 1e-3f * extent : extent, scale = rand_range(rng, 0.1f, 10);
        for (a = 0; a < 3; a++) {
            ray->org[a] = (float)(w[a] + from * rand_range(rng, -1, 1));
            ray->dir[a] = (float)((w[a] - ray->org[a]) * scale);
        }
        break;
    }
    case 3:
    case 4: { /* grazing, along axis a */
        static const float distances[] = {1.5f, 0.5f, 0.01f};
        const int axis = (int)rand_below(rng, 3);
        const float sign = rand_below(rng, 2) ? 1.0f : -1.0f;
        for (a = 0; a < 3; a++) {
            const unsigned step = rand_below(rng, 4);
            const float v = (float)w[a];
            ray->org[a] = step == 0 ? nextafterf(v, INFINITY) : step == 1 ? nextafterf(v, -INFINITY) : v;
            ray->dir[a] = grazing_components[rand_below(rng, (uint32_t)nc)];
        }
        ray->org[axis] = (float)(w[axis] - sign * distances[rand_below(rng, 3)] * extent);
        ray->dir[axis] = sign * (rand_below(rng, 2) ? 1.0f : 0.375f);
        break;
    }
    case 5:
    case 6: { /* a bounce: from the triangle, on it or a hair off either side */
        static const double hairs[] = {0, 1e-7, -1e-7, 1e-4, -1e-4};
        const double hair = len > 0 ? hairs[rand_below(rng, 5)] * extent / len : 0;
        for (a = 0; a < 3; a++) {
            ray->org[a] = (float)(w[a] + hair * n[a]);
            ray->dir[a] = rand_range(rng, -1, 1);
        }
        if (kind == 6)   /* a zero, subnormal or tiny component */
            ray->dir[rand_below(rng, 3)] = grazing_components[rand_below(rng, (uint32_t)nc)];
        if (rand_below(rng, 2)) ray->tnear = 1e-6f * extent;
        break;
    }
    default: { /* in the triangle's plane (to rounding): an edge's direction, or another */
        const double *e = rand_below(rng, 2) ? e1 : e2;
        const double back = rand_range(rng, 0.01f, 2);
        for (a = 0; a < 3; a++) {
            ray->dir[a] = (float)(rand_below(rng, 4) ? e[a] : e[a] + e1[a] + e2[a]);
            ray->org[a] = (float)(w[a] - back * ray->dir[a]);
        }
        break;
    }
    }
    if (rand_below(rng, 8) < 3 && entry_brute_hit(protos, inst, frames, count, ray, &hit)) {
        const unsigned cut = rand_below(rng, 3);
        if (cut == 0) ray->tnear = hit.t;                               /* [t, t] */
        if (cut == 2) ray->tnear = ray->tnear + (hit.t - ray->tnear) * brt_random_float(rng);
        if (cut <= 1) ray->tfar = hit.t;
    }
}

/*
** The clip's premise for instances: a batched ray's walk of a point of
** instances may start where its proxy cast first entered a set voxel
** (brt_proxy_raycast's t_entry) only if, for every hit that
** brt_instance_intersect reports at t_hit in [tnear, tfar], the cast over
** [tnear, tfar] returns 1 with t_entry <= t_hit (and the cull, which
** casts over [tnear, tlimit], needs the 1).  The voxel tests above check points
** against the voxels; this checks rays, the whole chain: the object ray's
** rounding, the triangle test's t, the dilation, the frame and the cast.
** Prototypes of lattice triangles, thin leaves and random ones, instanced
** under rotations, shears, mirrors, scales (and lattice-exact transforms,
** so that world triangles lie in axis planes), near the origin and 1e4
** from it in cells of 0.1 to 3, and 1e4 from it in cells of 0.008 to 0.1
** (10 to 100 float spacings there: the dilation is about one or less),
** voxelized into one grid at res 16..128 as
** instance_point_proxy does (the point's box grown by 1/16 of a voxel,
** dilated by INSTANCE_DILATION of a voxel, pruned); rays of entry_ray.
** Only the rays the batched mode casts count (proxy_cast: a ray whose
** margin, brt_instance_margin over the point's margin as slots_margin
** fits it, exceeds INSTANCE_DILATION of a voxel is admitted untested);
** the others are counted, and must stay few.  The transforms' condition
** numbers are bounded per resolution so that they do.
*/
static void test_instance_entry_before_hit(void)
{
    enum { ROUNDS = 48, RAYS = 6000, PROTOS = 3, MAX_INST = 10 };
    uint64_t rng = test_seed() + 4242, cast = 0, hits = 0, skipped = 0, fails = 0;
    int round;
    for (round = 0; round < ROUNDS; round++) {
        /* res 16, 32, 64, 128; near the origin, 1e4 from it, and 1e4 from
        ** it scaled by 2^-6 */
        const uint32_t res = 16u << (round % 4), count = 4 + rand_below(&rng, MAX_INST - 3);
        const int place = round / 4 % 3;
        const float scale = place == 2 ? 0x1p-6f : 1.0f, offset = place ? 1e4f : 0.0f;
        const float cond_max = 768.0f / (float)res;
        entry_proto protos[PROTOS];
        brt_instance inst[MAX_INST];
        brt_instance_frame frames[MAX_INST];
        float boxes[MAX_INST][6], radii[MAX_INST], lo[3], hi[3], glo[3], ghi[3], extent = 0;
        instance_margin margin;
        brt_grid grid;
        brt_svdag *dag = NULL;
        brt_proxy proxy;
        uint32_t i, n;
        int a, ok = 1;
        for (i = 0; i < PROTOS; i++) ok = entry_proto_make(&rng, (int)i, &protos[i]) && ok;
        CHECK(ok, "round %d: out of memory or prototype BVH", round);
        for (a = 0; a < 3; a++) { lo[a] = INFINITY; hi[a] = -INFINITY; }
        for (i = 0; i < count; i++) {
            float at[3];
            int tries = 0, j;
            for (a = 0; a < 3; a++) at[a] = offset + scale * rand_range(&rng, -6, 6);
            inst[i].prototype = rand_below(&rng, PROTOS);
            do {   /* a transform within the resolution's condition bound */
                if (rand_below(&rng, 4) == 0) {   /* lattice-exact: world axis planes */
                    const int *m = lattice_xforms[rand_below(&rng, sizeof lattice_xforms / sizeof lattice_xforms[0])];
                    for (j = 0; j < 12; j++) inst[i].xform[j] = j % 4 == 3 ? (float)(int)at[j / 4] : scale * (float)m[j];
                } else {
                    rotated_xform(&rng, inst[i].xform, at);
                    for (j = 0; j < 12; j++) if (j % 4 != 3) inst[i].xform[j] *= scale;
                }
                CHECK(++tries < 10000, "round %d: no transform within condition %g", round, cond_max);
            } while (brt_instance_frame_init(&inst[i], i, &frames[i], NULL) != BRT_OK ||
                     !(frames[i].condition <= cond_max));
            brt_instance_bounds(&inst[i], &frames[i], protos[inst[i].prototype].lo, protos[inst[i].prototype].hi,
                                boxes[i], boxes[i] + 3, &radii[i]);
            for (a = 0; a < 3; a++) {
                lo[a] = fminf(lo[a], boxes[i][a]);
                hi[a] = fmaxf(hi[a], boxes[i][3 + a]);
            }
        }
        /* the point's margin (slots_margin) and proxy (instance_point_proxy) */
        brt_margin_begin(&margin, lo, hi);
        for (i = 0; i < count; i++) brt_margin_add(&margin, &frames[i], radii[i]);
        for (a = 0; a < 3; a++) extent = fmaxf(extent, hi[a] - lo[a]);
        for (a = 0; a < 3; a++) {
            glo[a] = lo[a] - extent / (16.0f * (float)res);
            ghi[a] = hi[a] + extent / (16.0f * (float)res);
        }
        CHECK(brt_grid_init(&grid, glo, ghi, res) == BRT_OK, "round %d: grid", round);
        for (i = 0; i < count; i++)
            CHECK(brt_voxelize_instance(&grid, protos[inst[i].prototype].bvh, inst[i].xform,
                                        INSTANCE_DILATION * grid.cell, INSTANCE_VOXELS_PRUNED) == BRT_OK,
                  "round %d: voxelize instance %u", round, (unsigned)i);
        CHECK(brt_svdag_create(&dag) == BRT_OK && brt_svdag_add(dag, &grid, &proxy) == BRT_OK,
              "round %d: proxy", round);
        for (n = 0; n < RAYS; n++) {
            brt_ray ray;
            brt_hit hit;
            float t_entry = 0;
            int got;
            entry_ray(&rng, protos, inst, frames, count, lo, hi, extent, &ray);
            if (!(brt_instance_margin(margin.condition, margin.reach, margin.center, &ray) <=
                  INSTANCE_DILATION * proxy.cell)) {   /* admitted untested */
                skipped++;
                continue;
            }
            cast++;
            got = brt_proxy_raycast(dag, &proxy, &ray, ray.tnear, ray.tfar, &t_entry);
            if (!entry_brute_hit(protos, inst, frames, count, &ray, &hit)) continue;
            hits++;
            if (!(got && t_entry <= hit.t) && ++fails <= 5) {
                /* where the hit lies: on its triangle (the proxy's fault), or
                ** off it (the triangle test's t of a ray all but in the
                ** triangle's plane, clamped into its box: hit_distance) */
                static const double corner[3] = {1, 0, 0};
                double v0[3], e1[3], e2[3], v1[3], v2[3], at[3];
                entry_world_point(&protos[inst[hit.inst].prototype], hit.prim, inst[hit.inst].xform, corner,
                                  v0, e1, e2);
                for (a = 0; a < 3; a++) {
                    v1[a] = v0[a] + e1[a];
                    v2[a] = v0[a] + e2[a];
                    at[a] = ray.org[a] + (double)hit.t * ray.dir[a];
                }
                test_fail_at(__FILE__, __LINE__,
                             "round %d res %u (offset %g, scale %g): ray (%a %a %a) dir (%a %a %a) [%a %a] "
                             "hits instance %u triangle %u at t %a, proxy %d t %a; the hit's world point "
                             "lies %.3g voxels from the triangle (the dilation: %g)", round, res, offset,
                             scale, ray.org[0], ray.org[1], ray.org[2], ray.dir[0], ray.dir[1], ray.dir[2],
                             ray.tnear, ray.tfar, hit.inst, hit.prim, hit.t, got, t_entry,
                             tu_point_triangle_distance(at, v0, v1, v2) / proxy.cell, INSTANCE_DILATION);
            }
        }
        brt_svdag_free(dag);
        brt_grid_free(&grid);
        for (i = 0; i < PROTOS; i++) entry_proto_free(&protos[i]);
    }
    EXPECT(fails <= 5, "%llu rays in all hit an instance before the proxy's entry (5 shown)",
           (unsigned long long)fails);
    /* the gate lets most rays through, and enough of them hit */
    EXPECT(skipped * 4 < cast + skipped, "%llu of %llu rays admitted untested (margin)",
           (unsigned long long)skipped, (unsigned long long)(cast + skipped));
    EXPECT(hits * 4 > cast, "only %llu of %llu cast rays hit an instance", (unsigned long long)hits,
           (unsigned long long)cast);
    printf("  svdag: instances, entry before hit: %llu rays cast, %llu instance hits, %llu skipped (margin)\n",
           (unsigned long long)cast, (unsigned long long)hits, (unsigned long long)skipped);
}

void suite_svdag(void)
{
    test_run("svdag: grid frame covers the box", test_grid_frame);
    test_run("svdag: voxelizer vs exact lattice SAT", test_voxelizer_exact);
    test_run("svdag: voxelizer: non-lattice triangles touching voxels", test_voxelizer_non_lattice);
    test_run("svdag: voxelizer input", test_voxelizer_input);
    test_run("svdag: decode equals grid, res 2..1024", test_decode_every_resolution);
    test_run("svdag: raycast vs brute-force slabs", test_raycast_oracle);
    test_run("svdag: raycast special rays and proxies", test_raycast_special);
    test_run("svdag: end to end, shared meshes", test_end_to_end_shared);
    test_run("svdag: end to end, triangles on voxel faces", test_end_to_end_adversarial);
    test_run("svdag: end to end, tiny and huge scales", test_end_to_end_scales);
    test_run("svdag: dedup across proxies", test_dedup);
    test_run("svdag: blob round trip", test_blob_round_trip);
    test_run("svdag: corrupt blobs", test_blob_corrupt);
    test_run("svdag: voxelize program", test_voxelize_program);
    test_run("svdag: grazing directions, far origins", test_grazing_directions);
    test_run("svdag: grazing directions, inner proxies", test_grazing_inner);
    test_run("svdag: inner proxies, signed zeros in the weld", test_inner_signed_zeros);
    test_run("svdag: instances: lattice, sheared, mirrored, grazing", test_instance_voxels_lattice);
    test_run("svdag: instances: rotated thin triangles", test_instance_voxels_rotated);
    test_run("svdag: instances: pruned, a prototype in one voxel tests no triangle", test_instance_voxels_work);
    test_run("svdag: instances: the proxy is entered no later than any instance hit", test_instance_entry_before_hit);
}
