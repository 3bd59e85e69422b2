/*
** tests/test_referee.c -- the referee of hitdiff (examples/lib/referee.c) on
** hand-made rays and records, and build/hitdiff --mesh from outside.
**
** Every case is built so that its exact answer is known by construction
** (rays along axes through points with short binary fractions, a vertex
** reached by a direction that is an exact float difference): each class of
** referee.h is produced by a right pair of answers, and fabricated wrong
** answers (another prim, a t far off, a hit where the exact answer is a
** miss) must come out unexplained.  No Embree needed.
*/
#include "test.h"
#include "util.h"
#include "batchrt.h"
#include "../examples/lib/referee.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* The unit square z = 0 as two triangles sharing the diagonal x == y
** (prims 0 and 1), a huge triangle at z = 5 (prim 2), and prim 0 again
** lifted by 1e-7 (prim 3: a second surface closer than t can tell). */
static float square_positions[] = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0,
                                   -1e4f, -1e4f, 5, 1e4f, -1e4f, 5, 0, 1e4f, 5,
                                   0, 0, 1e-7f, 1, 0, 1e-7f, 1, 1, 1e-7f};
static uint32_t square_indices[] = {0, 1, 2, 0, 2, 3, 4, 5, 6, 7, 8, 9};
static const brt_mesh square = {square_positions, square_indices, 10, 4};

static const brt_hit miss = {INFINITY, BRT_NO_PRIM, 0, 0, BRT_NO_INST};

static brt_hit hit(uint32_t prim, float t)
{
    brt_hit h;
    h.t = t;
    h.prim = prim;
    h.u = h.v = 0.25f;
    h.inst = BRT_NO_INST;
    return h;
}

/* A ray straight down (-z) from (x, y, 1): it meets z = 0 at t = 1. */
static brt_ray down(float x, float y)
{
    brt_ray r = {{0, 0, 1}, {0, 0, -1}, 0, INFINITY};
    r.org[0] = x;
    r.org[1] = y;
    return r;
}

static void expect_class(const brt_mesh *mesh, const brt_ray *ray, brt_hit a, brt_hit b,
                         ex_class expected, const char *what)
{
    ex_verdict v;
    const ex_class got = ex_referee(mesh, ray, &a, &b, &v);
    EXPECT(got == expected, "%s: %s, expected %s (%s)", what, ex_class_id[got],
           ex_class_id[expected], v.text);
}

/* Through the shared diagonal exactly: both prims at t = 1 is a tie, and a
** miss or a farther hit on either side is that side's leak. */
static void test_shared_edge(void)
{
    const brt_ray r = down(0.5f, 0.5f);
    expect_class(&square, &r, hit(0, 1), hit(1, 1), EX_TIE, "both triangles of the edge");
    expect_class(&square, &r, hit(1, 1), hit(0, 1), EX_TIE, "the tie swapped");
    expect_class(&square, &r, hit(0, 1), miss, EX_LEAK_B, "B misses the edge");
    expect_class(&square, &r, miss, hit(1, 1), EX_LEAK_A, "A misses the edge");
    expect_class(&square, &r, hit(0, 1), hit(2, 6), EX_UNEXPLAINED,
                 "B's hit is behind the origin");
    /* At a corner of the square (a vertex of both prims). */
    {
        const brt_ray corner = down(1, 1);
        expect_class(&square, &corner, hit(0, 1), hit(1, 1), EX_TIE, "shared vertex");
        expect_class(&square, &corner, miss, hit(0, 1), EX_LEAK_A, "A misses the vertex");
    }
}

/* Fabricated wrong answers for a ray through the interior of prim 0. */
static void test_wrong_answers(void)
{
    const brt_ray r = down(0.75f, 0.25f), outside = down(1.25f, 0.5f);
    expect_class(&square, &r, hit(0, 1), hit(0, 1.0001f), EX_UNEXPLAINED, "t far off");
    expect_class(&square, &r, hit(0, 1), hit(1, 1), EX_UNEXPLAINED, "wrong prim");
    expect_class(&square, &r, hit(0, 1), miss, EX_UNEXPLAINED, "a miss through the interior");
    expect_class(&square, &r, miss, hit(0, 1), EX_UNEXPLAINED, "the same, swapped");
    expect_class(&square, &outside, miss, hit(0, 1), EX_UNEXPLAINED,
                 "a hit where the exact answer is a miss");
    expect_class(&square, &r, hit(0, 1), hit(2, 0.5f), EX_UNEXPLAINED,
                 "a hit on a triangle behind the origin");
    {
        const brt_ray nan_ray = {{NAN, 0, 1}, {0, 0, -1}, 0, INFINITY};
        expect_class(&square, &nan_ray, miss, hit(0, 1), EX_UNEXPLAINED, "a hit on a NaN ray");
    }
    /* Right answers still agree when only u, v differ. */
    {
        brt_hit b = hit(0, 1);
        b.u = 0.5f;
        expect_class(&square, &r, hit(0, 1), b, EX_T_BOUND, "u differs");
    }
}

/* One float step past the open edge x == 1: a hit there is rounding; a
** hit at x = 1.01 is not. */
static void test_just_outside(void)
{
    const brt_ray r = down(nextafterf(1.0f, 2.0f), 0.5f), far = down(1.01f, 0.5f);
    expect_class(&square, &r, miss, hit(0, 1), EX_OUTSIDE_B, "B hits one ulp outside");
    expect_class(&square, &r, hit(0, 1), miss, EX_OUTSIDE_A, "A hits one ulp outside");
    expect_class(&square, &far, miss, hit(0, 1), EX_UNEXPLAINED, "B hits 0.01 outside");
}

/* A ray that grazes the square (cos of incidence 1e-3): its t is 1000
** times worse conditioned than at normal incidence, so a t 1e-4 off is
** within its bound, but not for the ray straight down; 10 % is never. */
static void test_ill_conditioned(void)
{
    const brt_ray graze = {{-0.5f, 0.25f, 1e-3f}, {1, 0, -1e-3f}, 0, INFINITY};
    const brt_ray straight = down(0.75f, 0.25f);
    /* huge: prim 2 seen from just below, far from its vertices. */
    const brt_ray huge = {{0.3f, 0.1f, 4}, {0.6f, 0, 0.8f}, 0, INFINITY};
    const float t_huge = 1.25f;
    expect_class(&square, &graze, hit(0, 1), hit(0, 1.0001f), EX_T_BOUND, "grazing, 1e-4");
    expect_class(&square, &straight, hit(0, 1), hit(0, 1.0001f), EX_UNEXPLAINED,
                 "normal incidence, 1e-4");
    expect_class(&square, &graze, hit(0, 1), hit(0, 1.1f), EX_UNEXPLAINED, "grazing, 10 %");
    expect_class(&square, &huge, hit(2, t_huge), hit(2, t_huge * 1.0001f), EX_T_BOUND,
                 "close to a huge triangle, 1e-4");
    expect_class(&square, &huge, hit(2, t_huge), hit(2, t_huge * 1.5f), EX_UNEXPLAINED,
                 "close to a huge triangle, 50 %");
}

/* Hits at exactly tnear and tfar: the closed interval counts them, and a
** side that leaves them out is within rounding; a hit clearly before
** tnear is not. */
static void test_interval(void)
{
    brt_ray r = down(0.75f, 0.25f);
    r.tnear = 1;
    expect_class(&square, &r, hit(0, 1), miss, EX_BOUNDARY, "hit at exactly tnear");
    expect_class(&square, &r, miss, hit(0, 1), EX_BOUNDARY, "the same, swapped");
    r.tnear = 0;
    r.tfar = 1;
    expect_class(&square, &r, hit(0, 1), miss, EX_BOUNDARY, "hit at exactly tfar");
    /* The exact t is one ulp past tfar; B rounds it to tfar. */
    r.tfar = nextafterf(1.0f, 0.0f);
    expect_class(&square, &r, miss, hit(0, r.tfar), EX_BOUNDARY, "hit one ulp after tfar");
    expect_class(&square, &r, miss, hit(0, 1), EX_UNEXPLAINED, "a record t beyond tfar");
    r.tfar = INFINITY;
    r.tnear = 1.5f;
    expect_class(&square, &r, hit(0, 1), miss, EX_UNEXPLAINED, "hit before tnear");
}

/* Two surfaces 1e-7 apart (prims 0 and 3): the nearer one (3) is right,
** but reporting the farther is within the t bound. */
static void test_near_tie(void)
{
    const brt_ray r = down(0.75f, 0.25f);
    expect_class(&square, &r, hit(3, 1 - 1e-7f), hit(0, 1), EX_NEAR_TIE, "1e-7 apart");
    expect_class(&square, &r, hit(3, 0.9999999f), hit(2, 1), EX_UNEXPLAINED,
                 "a farther triangle that is not there");
}

/* The decisive predicate: a ray through a vertex shared by two triangles,
** at coordinates where the edge functions are not exact in double.  The
** direction is the exact float difference of the vertex and the origin, so
** the ray passes through the vertex exactly (t = 1): two edge functions of
** each triangle are exactly 0 and the answer is a tie.  Plain double
** arithmetic gives one of them as +1.9e-6, which would put prim 0 outside
** (found by a search over random such configurations in Python with exact
** rational arithmetic). */
static void test_exact_vertex(void)
{
    static float pos[] = {53816.293f, 34276.043f, 30385.3945f, 53818.1172f, 34276.043f,
                          30385.3945f, 53818.1172f, 34277.8672f, 30385.8516f,
                          53816.293f, 34277.8672f, 30385.8516f};
    static uint32_t idx[] = {0, 1, 2, 0, 2, 3};
    const brt_mesh mesh = {pos, idx, 4, 2};
    brt_ray r = {{-21398, -83376, 147010}, {0, 0, 0}, 0, INFINITY};
    int k;
    for (k = 0; k < 3; k++) {
        r.dir[k] = pos[6 + k] - r.org[k];
        CHECK((double)pos[6 + k] - r.org[k] == r.dir[k], "the direction is not exact");
    }
    expect_class(&mesh, &r, hit(0, 1), hit(1, 1), EX_TIE, "exact vertex tie");
    expect_class(&mesh, &r, hit(1, 1), miss, EX_LEAK_B, "B misses the exact vertex");
}


/* ===================================================================== */
/* Hard geometry: opposite facing, needles, slivers, each bound's edge   */
/* ===================================================================== */
/*
** The bounds of referee.c, written again here from their definitions
** (the top of referee.c), so that each class is checked just inside and
** just outside its bound: 0.9 and 1.1 of it.
**   edge band of edge ab: 16 FLT_EPSILON (|A| |B x d| + |B| |A x d|),
**     A = a - o, B = b - o;
**   t bound: 16 FLT_EPSILON (L1 L2 (R + |t| |d|) / |D| + |t|), L1 and L2
**     the two longest edges, R the farthest vertex from o, D = d . n.
*/
static double len3(const double v[3]) { return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

static void cross3(const double a[3], const double b[3], double c[3])
{
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

static double band_of(const brt_ray *r, const float *a, const float *b)
{
    double A[3], B[3], d[3], Ad[3], Bd[3];
    int k;
    for (k = 0; k < 3; k++) {
        A[k] = (double)a[k] - r->org[k];
        B[k] = (double)b[k] - r->org[k];
        d[k] = r->dir[k];
    }
    cross3(A, d, Ad);
    cross3(B, d, Bd);
    return 16 * FLT_EPSILON * (len3(A) * len3(Bd) + len3(B) * len3(Ad));
}

static double t_bound_of(const brt_mesh *m, uint32_t prim, const brt_ray *r, double t)
{
    const float *v[3];
    double e[3], n[3], e1[3], e2[3], d[3], far = 0, l1, l2;
    int i, k;
    for (i = 0; i < 3; i++) v[i] = m->positions + 3 * (size_t)m->indices[3 * prim + i];
    for (i = 0; i < 3; i++) {
        double w[3], f[3];
        for (k = 0; k < 3; k++) {
            f[k] = (double)v[(i + 1) % 3][k] - v[i][k];
            w[k] = (double)v[i][k] - r->org[k];
        }
        e[i] = len3(f);
        far = fmax(far, len3(w));
    }
    for (k = 0; k < 3; k++) {
        e1[k] = (double)v[1][k] - v[0][k];
        e2[k] = (double)v[2][k] - v[0][k];
        d[k] = r->dir[k];
    }
    cross3(e1, e2, n);
    l1 = fmax(e[0], fmax(e[1], e[2]));
    l2 = e[0] + e[1] + e[2] - l1 - fmin(e[0], fmin(e[1], e[2]));
    return 16 * FLT_EPSILON * (l1 * l2 * (far + fabs(t) * len3(d)) /
                               fabs(d[0] * n[0] + d[1] * n[1] + d[2] * n[2]) + fabs(t));
}

/* Opposite-facing triangles: prim 0 at z = 0 wound counter-clockwise seen
** from above, prim 1 the same square corner at z = -gap wound clockwise
** (its D has the other sign).  A ray down meets 0 at t = 1, 1 at 1 + gap. */
static void test_opposite_facing(void)
{
    static const float gaps[] = {0.5f, 1e-3f};
    size_t g;
    for (g = 0; g < sizeof gaps / sizeof *gaps; g++) {
        float pos[] = {0, 0, 0, 2, 0, 0, 0, 2, 0, 0, 0, 0, 0, 2, 0, 2, 0, 0};
        static uint32_t idx[] = {0, 1, 2, 3, 4, 5};
        const brt_mesh m = {pos, idx, 6, 2};
        const brt_ray r = down(0.5f, 0.25f);
        const float far_t = 1 + gaps[g];
        int k;
        for (k = 3; k < 6; k++) pos[3 * k + 2] = -gaps[g];
        expect_class(&m, &r, hit(1, far_t), hit(0, 1), EX_UNEXPLAINED, "A skips the nearer, facing away");
        expect_class(&m, &r, hit(0, 1), hit(1, far_t), EX_UNEXPLAINED, "B skips the nearer, facing away");
        /* The nearer one facing away: swap the windings. */
        pos[3] = 0, pos[4] = 2, pos[6] = 2, pos[7] = 0;
        pos[12] = 2, pos[13] = 0, pos[15] = 0, pos[16] = 2;
        expect_class(&m, &r, hit(1, far_t), hit(0, 1), EX_UNEXPLAINED, "A skips the nearer, facing toward");
        expect_class(&m, &r, hit(0, 1), hit(1, far_t), EX_UNEXPLAINED, "B skips the nearer, facing toward");
    }
}

/* Same prim, t off by 0.9 and 1.1 of its t bound: within it, t_bound;
** beyond it, unexplained.  On a well-shaped triangle, a needle (one edge
** 1e-3 long), and a sliver (height 1e-3 over a unit edge). */
static void test_t_bound_edges(void)
{
    static float pos[] = {0, 0, 0, 1, 0, 0, 0, 1, 0,            /* well shaped */
                          0, 0, 0, 1e-3f, 0, 0, 0.5f, 1, 0,     /* needle */
                          0, 0, 0, 1, 0, 0, 0.5f, 1e-3f, 0};    /* sliver */
    static uint32_t idx[] = {0, 1, 2, 3, 4, 5, 6, 7, 8};
    static const float at[3][2] = {{0.25f, 0.25f}, {0.25f, 0.5f}, {0.5f, 2.5e-4f}};
    static const char *const name[3] = {"well shaped", "needle", "sliver"};
    const brt_mesh m = {pos, idx, 9, 3};
    uint32_t p;
    for (p = 0; p < 3; p++) {
        const brt_ray r = down(at[p][0], at[p][1]);
        const double b = t_bound_of(&m, p, &r, 1.0);
        char what[96];
        ex_verdict v;
        brt_hit h = hit(p, (float)(1 + 0.9 * b));
        snprintf(what, sizeof what, "%s, t off by 0.9 of its bound %.3g", name[p], b);
        expect_class(&m, &r, hit(p, 1), h, EX_T_BOUND, what);
        ex_referee(&m, &r, &h, &h, &v);
        EXPECT(fabs(v.t_ratio - ((double)h.t - 1) / b) < 1e-3, "%s: t ratio %g, expected %g", what,
               v.t_ratio, ((double)h.t - 1) / b);
        snprintf(what, sizeof what, "%s, t off by 1.1 of its bound %.3g", name[p], b);
        expect_class(&m, &r, hit(p, 1), hit(p, (float)(1 + 1.1 * b)), EX_UNEXPLAINED, what);
    }
}

/* Two triangles, the second (opposite facing) gap farther: reporting it
** is a near tie while gap is within 0.9 of the sum of their t bounds,
** unexplained at 1.1. */
static void test_near_tie_edges(void)
{
    static const double share[2] = {0.9, 1.1};
    int i;
    for (i = 0; i < 2; i++) {
        float pos[] = {0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0, 0, 1, 0, 1, 0, 0};
        static uint32_t idx[] = {0, 1, 2, 3, 4, 5};
        const brt_mesh m = {pos, idx, 6, 2};
        const brt_ray r = down(0.25f, 0.25f);
        const double sum = t_bound_of(&m, 0, &r, 1.0) + t_bound_of(&m, 1, &r, 1.0);
        const float gap = (float)(share[i] * sum);
        char what[96];
        int k;
        for (k = 3; k < 6; k++) pos[3 * k + 2] = -gap;
        snprintf(what, sizeof what, "the farther of two, %.1f of the bounds' sum %.3g", share[i], sum);
        expect_class(&m, &r, hit(1, 1 + gap), hit(0, 1), i == 0 ? EX_NEAR_TIE : EX_UNEXPLAINED, what);
    }
}

/* A ray inside or outside the edge x = 1 of the triangle (0,0) (1,0)
** (1,1) by 0.9 and 1.1 of the edge band: a miss inside it is a leak, a hit
** outside it is rounding; beyond the band, both are unexplained. */
static void test_edge_band_edges(void)
{
    static float pos[] = {0, 0, 0, 1, 0, 0, 1, 1, 0};
    static uint32_t idx[] = {0, 1, 2};
    const brt_mesh m = {pos, idx, 3, 1};
    static const double share[2] = {0.9, 1.1};
    int i, side;
    for (side = -1; side <= 1; side += 2)
        for (i = 0; i < 2; i++) {
            brt_ray r = down(1, 0.5f);
            char what[96];
            int step;
            /* the float x whose distance from the edge is nearest share * band */
            for (step = 0; step < 1000; step++) {
                const float x = nextafterf(r.org[0], side < 0 ? 0.0f : 2.0f);
                brt_ray next = down(x, 0.5f);
                if (fabs((double)x - 1) > share[i] * band_of(&next, pos + 3, pos + 6)) break;
                r = next;
            }
            snprintf(what, sizeof what, "%s the edge by %.2f of its band", side < 0 ? "inside" : "outside",
                     fabs((double)r.org[0] - 1) / band_of(&r, pos + 3, pos + 6));
            if (side < 0) expect_class(&m, &r, miss, hit(0, 1), i == 0 ? EX_LEAK_A : EX_UNEXPLAINED, what);
            else expect_class(&m, &r, miss, hit(0, 1), i == 0 ? EX_OUTSIDE_B : EX_UNEXPLAINED, what);
        }
}

/* The exact t before tnear by 0.9 and 1.1 of its t bound, the record at
** tnear: the boundary's rounding, then unexplained. */
static void test_boundary_edges(void)
{
    static float pos[] = {0, 0, 0, 1, 0, 0, 0, 1, 0};
    static uint32_t idx[] = {0, 1, 2};
    const brt_mesh m = {pos, idx, 3, 1};
    static const double share[2] = {0.9, 1.1};
    int i;
    for (i = 0; i < 2; i++) {
        brt_ray r = down(0.25f, 0.25f);
        char what[96];
        r.tnear = (float)(1 + share[i] * t_bound_of(&m, 0, &r, 1.0));
        snprintf(what, sizeof what, "the hit %.1f of its bound before tnear", share[i]);
        expect_class(&m, &r, hit(0, r.tnear), miss, i == 0 ? EX_BOUNDARY : EX_UNEXPLAINED, what);
    }
}

/* ===================================================================== */
/* Occlusion records                                                     */
/* ===================================================================== */

static void expect_occlusion(const brt_ray *ray, int a, int b, ex_class expected,
                             const char *what)
{
    ex_verdict v;
    const ex_class got = ex_referee_occlusion(&square, ray, a, b, &v);
    EXPECT(got == expected, "%s: %s, expected %s (%s)", what, ex_class_id[got],
           ex_class_id[expected], v.text);
}

/* The square's rays as occlusion records: no record names a triangle, so
** the referee must find the triangles among its candidates itself.  The
** huge prim 2 (z = 5) is behind every origin (z = 1) until tnear = -inf;
** prim 3 lies 1e-7 above prim 0 (x > y), so rays through prim 0 hit both,
** and rays through prim 1 (x < y) hit prim 1 only. */
static void test_occlusion_referee(void)
{
    brt_ray edge = down(0.5f, 0.5f), middle = down(0.75f, 0.25f), far = down(3, 3);
    brt_ray near_edge = down(nextafterf(1.0f, 2.0f), 0.5f), at_tfar = down(0.25f, 0.75f);
    /* Through the shared diagonal x == y of prims 0 and 1 (and the edge
    ** x == y of prim 3): every exact hit is at an edge. */
    expect_occlusion(&edge, 0, 1, EX_LEAK_A, "A says clear through the shared edge");
    expect_occlusion(&edge, 1, 0, EX_LEAK_B, "B says clear through the shared edge");
    /* Through the middle of prim 0 (and 3): a 0 is wrong. */
    expect_occlusion(&middle, 0, 1, EX_UNEXPLAINED, "A says clear through prim 0's middle");
    /* Far from every triangle (the huge prim 2 is behind the origin): a 1
    ** is wrong. */
    expect_occlusion(&far, 1, 0, EX_UNEXPLAINED, "A says occluded far from everything");
    far.tnear = -INFINITY;   /* now prim 2 lies on the segment, well inside */
    expect_occlusion(&far, 1, 0, EX_UNEXPLAINED, "B says clear through prim 2");
    /* A hit well inside decides, even when the ray also passes an edge. */
    edge.tnear = -INFINITY;
    expect_occlusion(&edge, 0, 1, EX_UNEXPLAINED, "A says clear through prim 2 and an edge");
    /* One float step outside x == 1: only rounding can hit prim 0. */
    expect_occlusion(&near_edge, 0, 1, EX_OUTSIDE_B, "B says occluded one ulp outside");
    /* Through prim 1 only (x < y, where prim 3 is absent), whose exact t
    ** is 1 == tfar: the closed interval counts the hit, so 1 is right and
    ** 0 is the boundary's rounding; one ulp before, the hit is not on the
    ** segment, and 1 is the boundary's rounding. */
    at_tfar.tfar = 1;
    expect_occlusion(&at_tfar, 1, 0, EX_BOUNDARY, "B says clear at exactly tfar");
    at_tfar.tfar = nextafterf(1.0f, 0.0f);
    expect_occlusion(&at_tfar, 0, 1, EX_BOUNDARY, "B says occluded one ulp past tfar");
    at_tfar.tfar = 0.5f;
    expect_occlusion(&at_tfar, 0, 1, EX_UNEXPLAINED, "B says occluded far past tfar");
}

/* ===================================================================== */
/* build/hitdiff --mesh from outside                                     */
/* ===================================================================== */

/* The square as an OBJ, four rays, and two hit files that disagree on
** three rays: a tie, a leak and (when wrong) a t far off. */
static int write_case(int wrong)
{
    static const char obj[] = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n";
    brt_ray rays[4];
    brt_hit a[4], b[4];
    rays[0] = down(0.5f, 0.5f);
    rays[1] = down(0.5f, 0.5f);
    rays[2] = down(0.75f, 0.25f);
    rays[3] = down(3, 3);
    a[0] = hit(0, 1), b[0] = hit(1, 1);
    a[1] = hit(0, 1), b[1] = miss;
    a[2] = hit(0, 1), b[2] = hit(0, wrong ? 1.5f : 1);
    a[3] = miss, b[3] = miss;
    return tu_spill(tu_scratch("ref.obj"), obj, sizeof obj - 1)
           && brt_rays_write(tu_scratch("ref.rays"), rays, 4, NULL) == BRT_OK
           && brt_hits_write(tu_scratch("ref_a.hits"), a, 4, NULL) == BRT_OK
           && brt_hits_write(tu_scratch("ref_b.hits"), b, 4, NULL) == BRT_OK;
}

static int output_has(const char *text)
{
    char *out = tu_last_stdout();
    const int found = out && strstr(out, text);
    free(out);
    return found;
}

static void test_hitdiff_referee(void)
{
    char *csv;
    int status;
    CHECK(write_case(0), "cannot write the files");
    status = tu_run("hitdiff @/ref_a.hits @/ref_b.hits --mesh @/ref.obj --rays @/ref.rays "
                    "--explain @/ref.csv");
    EXPECT(status == 0, "hitdiff: exit status %d, expected 0", status);
    EXPECT(output_has("EXPLAINED: all 2 disagreeing rays of 4 explained"), "no verdict line");
    EXPECT(output_has("B leaks through an edge or vertex               1"), "no leak row");
    csv = (char *)tu_slurp(tu_scratch("ref.csv"), NULL);
    CHECK(csv, "no CSV written");
    EXPECT(strstr(csv, "ray,class,a_t,a_prim,a_u,a_v,b_t,b_prim,b_u,b_v,verdict\n0,tie,1,0,")
           && strstr(csv, "\n1,leak_b,1,0,0.25,0.25,inf,-1,0,0,\"A: prim 0 at an edge;")
           && !strstr(csv, "\n2,"), "CSV:\n%s", csv);
    free(csv);

    CHECK(write_case(1), "cannot write the files");
    status = tu_run("hitdiff @/ref_a.hits @/ref_b.hits --mesh @/ref.obj --rays @/ref.rays "
                    "--explain @/ref.csv");
    EXPECT(status == 1, "a t far off: exit status %d, expected 1", status);
    EXPECT(output_has("UNEXPLAINED: 1 of 3 disagreeing rays of 4 unexplained"),
           "no UNEXPLAINED line");
    csv = (char *)tu_slurp(tu_scratch("ref.csv"), NULL);
    EXPECT(csv && strstr(csv, "\n2,unexplained,1,0,"), "CSV:\n%s", csv ? csv : "(none)");
    free(csv);
    EXPECT(!tu_temporary_file_left(), "a temporary file was left behind");
}

/* The same square and rays as occlusion files: ray 0 (the shared edge)
** leaks in B, ray 2 (prim 0's middle) is clear in B when wrong, ray 3
** (far away) agrees. */
static void test_hitdiff_occlusion_referee(void)
{
    static const uint8_t a[4] = {1, 1, 1, 0}, right[4] = {1, 0, 1, 0}, wrong[4] = {1, 0, 0, 0};
    char *csv;
    int status;
    CHECK(write_case(0) && tu_spill(tu_scratch("ref_a.occ"), a, 4)
          && tu_spill(tu_scratch("ref_b.occ"), right, 4)
          && tu_spill(tu_scratch("ref_w.occ"), wrong, 4), "cannot write the files");
    status = tu_run("hitdiff @/ref_a.occ @/ref_b.occ --occlusion --mesh @/ref.obj "
                    "--rays @/ref.rays --explain @/ref.csv");
    EXPECT(status == 0, "hitdiff --occlusion --mesh: exit status %d, expected 0", status);
    EXPECT(output_has("EXPLAINED: all 1 disagreeing rays of 4 explained"), "no verdict line");
    csv = (char *)tu_slurp(tu_scratch("ref.csv"), NULL);
    EXPECT(csv && strstr(csv, "ray,class,a,b,verdict\n1,leak_b,1,0,\"A: 1; B: 0;"),
           "CSV:\n%s", csv ? csv : "(none)");
    free(csv);
    status = tu_run("hitdiff @/ref_a.occ @/ref_w.occ --occlusion --mesh @/ref.obj "
                    "--rays @/ref.rays --explain @/ref.csv");
    EXPECT(status == 1, "a 0 through a middle: exit status %d, expected 1", status);
    EXPECT(output_has("UNEXPLAINED: 1 of 2 disagreeing rays of 4 unexplained"),
           "no UNEXPLAINED line");
    EXPECT(tu_run("hitdiff @/ref_a.occ @/ref_b.occ --occlusion") == 1
           && output_has("occluded in A only"), "without --mesh: not the byte comparison");
    EXPECT(!tu_temporary_file_left(), "a temporary file was left behind");
}

/* Bad input: one line on stderr naming the file, no CSV. */
static void expect_bad(int expected_status, const char *args, const char *words)
{
    char *err;
    int status;
    remove(tu_scratch("bad.csv"));
    status = tu_run("hitdiff %s%s", args, strstr(args, "--explain") ? "" : " --explain @/bad.csv");
    err = tu_last_stderr();
    EXPECT(status == expected_status, "%s: exit status %d, expected %d", args, status,
           expected_status);
    EXPECT(err && strstr(err, words) && strchr(err, '\n') == err + strlen(err) - 1,
           "%s: stderr '%s' lacks '%s' or is not one line", args, err ? err : "", words);
    EXPECT(!tu_file_exists(tu_scratch("bad.csv")), "%s: wrote a CSV", args);
    free(err);
}

static void test_hitdiff_bad_input(void)
{
    brt_hit far_prim = {1, 7, 0, 0, BRT_NO_INST};
    CHECK(write_case(0), "cannot write the files");
    CHECK(brt_hits_write(tu_scratch("ref_short.hits"), &far_prim, 1, NULL) == BRT_OK
          && brt_hits_write(tu_scratch("ref_prim.hits"), &far_prim, 1, NULL) == BRT_OK
          && brt_rays_write(tu_scratch("ref_one.rays"), (const brt_ray[]){down(0.5f, 0.5f)}, 1,
                            NULL) == BRT_OK,
          "cannot write the files");
    expect_bad(1, "@/ref_a.hits @/ref_b.hits --mesh @/none.obj --rays @/ref.rays", "none.obj");
    expect_bad(1, "@/ref_a.hits @/ref_b.hits --mesh @/ref.obj --rays @/none.rays", "none.rays");
    expect_bad(2, "@/ref_a.hits @/ref_b.hits --mesh @/ref.obj --rays @/ref_one.rays",
               "ref_one.rays has 1 rays");
    expect_bad(2, "@/ref_a.hits @/ref_short.hits --mesh @/ref.obj --rays @/ref.rays",
               "ref_short.hits");
    expect_bad(1, "@/ref_prim.hits @/ref_prim.hits --mesh @/ref.obj --rays @/ref_one.rays",
               "ref_prim.hits: record 0: prim 7 beyond the 2 triangles");
    expect_bad(1, "@/ref_a.hits @/ref_b.hits --mesh @/ref.obj", "--rays");
    expect_bad(1, "@/ref_a.hits @/ref_b.hits --mesh @/ref.obj --rays @/ref.rays --t-rel 0.1",
               "--t-rel");
    expect_bad(1, "@/ref_a.hits @/ref_b.hits --mesh @/ref.obj --rays @/ref.rays "
               "--explain @/no/such/dir.csv", "no/such/dir.csv");
}

void suite_referee(void)
{
    test_run("referee: a ray through a shared edge or vertex: tie, or a leak", test_shared_edge);
    test_run("referee: fabricated wrong answers are unexplained", test_wrong_answers);
    test_run("referee: a hit one ulp outside an edge is rounding", test_just_outside);
    test_run("referee: the t bound follows the ray's conditioning", test_ill_conditioned);
    test_run("referee: hits at exactly tnear and tfar", test_interval);
    test_run("referee: two surfaces closer than t can tell", test_near_tie);
    test_run("referee: an exact vertex where double arithmetic errs", test_exact_vertex);
    test_run("referee: hard geometry, opposite-facing triangles", test_opposite_facing);
    test_run("referee: hard geometry, the t bound on needles and slivers", test_t_bound_edges);
    test_run("referee: hard geometry, a near tie at its bound", test_near_tie_edges);
    test_run("referee: hard geometry, the edge band at its bound", test_edge_band_edges);
    test_run("referee: hard geometry, tnear at its bound", test_boundary_edges);
    test_run("referee: occlusion records: leak, outside, tfar, fabricated 0 and 1",
             test_occlusion_referee);
    test_run("referee: hitdiff --mesh table, exit status and --explain",
             test_hitdiff_referee);
    test_run("referee: hitdiff --occlusion --mesh table, exit status and --explain",
             test_hitdiff_occlusion_referee);
    test_run("referee: hitdiff --mesh rejects bad input in one line", test_hitdiff_bad_input);
}
