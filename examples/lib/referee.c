/*
** examples/lib/referee.c -- the referee of two closest-hit records (referee.h).
**
** QUESTION.  Two tracers answered "what does this ray hit first?"
** differently.  Each answer names a triangle (or none).  For each named
** triangle the referee decides, exactly, where the ray meets it: inside,
** on an edge or vertex, or outside; and where along the ray: before tnear,
** inside [tnear, tfar], after tfar; and which of two triangles comes
** first.  Then it asks whether each answer is right, or wrong only by the
** rounding any float ray/triangle test commits (the bounds below), and
** sorts the ray into one class of referee.h.
**
** THE EXACT PREDICATES.  With o, d the ray and a, b, c a triangle (all
** floats, so exact rationals), everything is decided by signs of three
** polynomials, each a sum of products of three input floats:
**   E_ab = d . ((a - o) x (b - o))          edge function of edge ab
**        = d . (a x b + b x o + o x a)      (Pluecker's form: no differences)
**   D    = d . ((b - a) x (c - a))          = E_ab + E_bc + E_ca
**   N    = (a - o) . ((b - a) x (c - a))    = det[a,b,c] - det[o,b,c]
**                                             - det[a,o,c] - det[a,b,o]
** The ray's line passes through the closed triangle exactly when no E has
** the sign opposite to D's; an E of 0 means through that edge's line (two
** zeros: through a vertex).  The plane is met at t = N / D, and
** "t >= tnear" is sign((N - tnear D) D) >= 0, "t_X < t_Y" for two triangles
** is sign(N_X D_Y - N_Y D_X) sign(D_X D_Y) < 0: products of up to six floats.
**
** WHAT "EXACT" MEANS HERE.  Every such sign is the sign of the exact real
** value of the polynomial in the input floats, with no tolerance.  The
** products and sums are carried out on floating-point expansions (Shewchuk,
** "Adaptive Precision Floating-Point Arithmetic and Fast Robust Geometric
** Predicates", 1997): a value is held as a sum of doubles that do not
** overlap, and two_sum / two_product return the rounding error of a sum or
** product as a second double, so nothing is ever lost.  The product of two
** floats is exact in a double (24 + 24 <= 53 bits); every product of up to
** six floats lies between 2^-894 and 2^768 in magnitude, inside double's
** normal range, so the error terms neither overflow nor underflow: the
** signs are exact for all finite inputs.  Where rounding still enters:
**   - t itself: N / D is rounded to a double (relative error ~1e-16), and
**     the distance of an edge or of t from tnear or tfar is measured in
**     double; these only feed the bounds below, never a sign;
**   - the bounds: whether a wrong answer is "within rounding" of a float
**     test is a model of such tests (the bounds below), not a theorem about
**     a particular tracer.
**
** THE BOUNDS (what a float ray/triangle test may get wrong).
**   Edge band.  A float test evaluates each edge function from the vertices
**   relative to the origin, A = a - o and B = b - o, rounded: |dA| <=
**   k eps |A| (Woop et al. shear them too, which at most doubles k;
**   Moeller-Trumbore and Pluecker tests use the same differences).  To first
**   order E = d . (A x B) = A . (B x d) moves by
**     |dE| <= |dA| |B x d| + |dB| |A x d| <= k eps (|A| |B x d| + |B| |A x d|),
**   and |B x d| = |d| times the distance of b from the ray's line, which is
**   at most the triangle's size when the ray passes through it.  So
**     band_ab = EDGE_ULPS * FLT_EPSILON * (|A| |B x d| + |B| |A x d|),
**   EDGE_ULPS = 16 covering k, the shear and the roundings of the products.
**   A ray whose |E_ab| is within band_ab of 0 passes "at" that edge: a float
**   test may put it on either side.
**   t bound.  A float test computes t = N / D from a rounded normal
**   n = (b - a) x (c - a) (|dn| <= k eps L1 L2, L1, L2 the two longest
**   edges: a sliver's normal is relatively much worse than eps |n|) and
**   rounded differences (|d(a - o)| <= k eps R, R the largest |v - o|):
**     |dN| <= k eps L1 L2 R,  |dD| <= k eps L1 L2 |d|,
**     |dt| = |dN - t dD| / |D| <= k eps L1 L2 (R + |t| |d|) / |D|,
**   plus half an ulp for storing t as a float.  So
**     t_bound = T_ULPS * FLT_EPSILON * (L1 L2 (R + |t| |d|) / |D| + |t|).
**   |D| = |n| |d| cos(incidence): the bound grows as 1 / cos for grazing
**   rays and as R / t for a ray that starts close to a large triangle; for
**   a ray at normal incidence on a well-shaped triangle it is a few ulps of
**   t.  (batchrt itself computes t from the plane equation in double and is
**   within an ulp or two; Embree's float Moeller-Trumbore is what needs
**   the bound.)
**
** OCCLUSION.  An occlusion record (a byte per ray, no triangle) names no
** triangle, so the referee finds the candidates itself: by brute force
** over the mesh, every triangle whose box, padded (occlusion_pad), the
** segment [tnear, tfar] enters by a float slab test.  The padding makes the
** float test conservative: a triangle the exact ray hits within [tnear,
** tfar], or passes within an edge band of, or meets within a t bound of
** tnear or tfar (both bounds are far below the padding), is a candidate.
** Each candidate is judged by judge_triangle() exactly as above; the
** exact answer is 1 when some candidate is hit (inside or on an edge) with
** tnear <= t <= tfar.  Cost: one box test per triangle and per disagreeing
** ray (agreeing rays are never refereed), plus the exact judgement of the
** few candidates.  Where the float box test could still drop a triangle
** that matters: a t bound longer than the padding (a ray grazing its
** triangle at well under a degree, hitting it within that bound of tnear
** or tfar); such a ray comes out unexplained, never wrongly explained.
*/
#include "referee.h"
#include "common.h"

#include <float.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define EDGE_ULPS 16.0
#define T_ULPS 16.0

const char *const ex_class_id[EX_CLASSES] = {
    "tie", "near_tie", "t_bound", "leak_a", "leak_b", "outside_a", "outside_b", "boundary",
    "transform", "unexplained"};
const char *const ex_class_label[EX_CLASSES] = {
    "tie (both right, same exact t)",
    "near tie (exact t within the bound)",
    "same prim, t within the bound",
    "A leaks through an edge or vertex",
    "B leaks through an edge or vertex",
    "A hits just outside an edge",
    "B hits just outside an edge",
    "tnear/tfar boundary",
    "within the instance transform",
    "unexplained"};

/* ===================================================================== */
/* Floating-point expansions (Shewchuk 1997)                             */
/* ===================================================================== */
/*
** An expansion is a value held as an unevaluated sum of doubles, ordered by
** increasing magnitude, no two overlapping (the lowest set bit of each is
** above the highest of the one before) and none zero.  Its sign is then the
** sign of its largest component.  The doubles are exact: every operation
** below returns the exact result, its own rounding error included.
*/

/* Room for the longest expansion built below.  Accumulations compress (see
** exp_compress) whenever they fill up; a compressed expansion of one of our
** values is a handful of components, so EXP_CAP is never reached in
** practice.  If it were, the expansion is marked overflowed and the
** referee answers "unexplained" rather than guess. */
#define EXP_CAP 96

typedef struct expansion {
    int n;                 /* components in use */
    int overflow;          /* ran out of room: the value is not known */
    double c[EXP_CAP];
} expansion;

/* x + y == a + b exactly, x = fl(a + b) (Knuth's TwoSum: no precondition). */
static void two_sum(double a, double b, double *x, double *y)
{
    const double s = a + b;
    const double b_part = s - a;          /* what of b made it into s */
    const double a_part = s - b_part;     /* what of a made it into s */
    *x = s;
    *y = (a - a_part) + (b - b_part);
}

/* The same when |a| >= |b| (Dekker's FastTwoSum, one subtraction less). */
static void fast_two_sum(double a, double b, double *x, double *y)
{
    const double s = a + b;
    *x = s;
    *y = b - (s - a);
}

/* a == hi + lo with hi and lo of at most 26 significant bits each, so that
** products of halves are exact (Veltkamp's split, 2^27 + 1). */
static void split(double a, double *hi, double *lo)
{
    const double c = 134217729.0 * a;
    *hi = c - (c - a);
    *lo = a - *hi;
}

/* x + y == a * b exactly, x = fl(a * b) (Dekker's TwoProduct): the four
** half-products are exact, and subtracting them from x one by one leaves
** the rounding error of x.  Needs -ffp-contract=off (the Makefile's). */
static void two_product(double a, double b, double *x, double *y)
{
    double ah, al, bh, bl;
    const double p = a * b;
    split(a, &ah, &al);
    split(b, &bh, &bl);
    *x = p;
    *y = al * bl - (((p - ah * bh) - al * bh) - ah * bl);
}

/* Shewchuk's COMPRESS: one sweep from the largest component down merges
** neighbours while their sum fits in one double, a sweep back up does it
** again; the value is unchanged, in the fewest components, and the largest
** then approximates the whole to within its own ulp. */
static void exp_compress(expansion *e)
{
    double g[EXP_CAP], q, x, y;
    int i, bottom, top = 0;
    if (e->n == 0) return;
    bottom = e->n - 1;
    q = e->c[e->n - 1];
    for (i = e->n - 2; i >= 0; i--) {
        fast_two_sum(q, e->c[i], &x, &y);
        if (y != 0.0) {
            g[bottom--] = x;
            q = y;
        } else {
            q = x;
        }
    }
    for (i = bottom + 1; i < e->n; i++) {
        fast_two_sum(g[i], q, &x, &y);
        if (y != 0.0) e->c[top++] = y;
        q = x;
    }
    if (q != 0.0) e->c[top++] = q;
    e->n = top;
}

/* e += b exactly (Shewchuk's GROW-EXPANSION with zero elimination): b is
** carried up through the components, each two_sum leaving its error behind
** as a new, smaller component. */
static void exp_add(expansion *e, double b)
{
    double q = b, h;
    int i, m = 0;
    if (b == 0.0) return;
    if (e->n >= EXP_CAP - 1) exp_compress(e);
    if (e->n >= EXP_CAP - 1) {
        e->overflow = 1;
        return;
    }
    for (i = 0; i < e->n; i++) {
        two_sum(q, e->c[i], &q, &h);
        if (h != 0.0) e->c[m++] = h;
    }
    if (q != 0.0) e->c[m++] = q;
    e->n = m;
}

/* e += x * y exactly: two_product's two parts. */
static void exp_add_product(expansion *e, double x, double y)
{
    double hi, lo;
    two_product(x, y, &hi, &lo);
    exp_add(e, lo);
    exp_add(e, hi);
}

/* e += scale * f exactly (scale = +-1 for sums and differences). */
static void exp_add_scaled(expansion *e, const expansion *f, double scale)
{
    int i;
    for (i = 0; i < f->n; i++) exp_add_product(e, f->c[i], scale);
    e->overflow |= f->overflow;
}

/* out = f * g exactly: every pair of components. */
static void exp_multiply(const expansion *f, const expansion *g, expansion *out)
{
    int i, j;
    out->n = 0;
    out->overflow = f->overflow | g->overflow;
    for (i = 0; i < f->n; i++)
        for (j = 0; j < g->n; j++) exp_add_product(out, f->c[i], g->c[j]);
    exp_compress(out);
}

static int exp_sign(const expansion *e)
{
    return e->n == 0 ? 0 : (e->c[e->n - 1] > 0.0 ? 1 : -1);
}

/* The value rounded to a double (smallest components first). */
static double exp_value(const expansion *e)
{
    double s = 0.0;
    int i;
    for (i = 0; i < e->n; i++) s += e->c[i];
    return s;
}

/* ===================================================================== */
/* The ray's polynomials of one triangle                                 */
/* ===================================================================== */

/* e += s * r . (p x q), the triple product det[p, q, r], exactly: each of
** its six terms is a product of three floats, the first two exact in a
** double, the third by two_product.  s is +1 or -1. */
static void add_triple(expansion *e, double s, const float *p, const float *q, const float *r)
{
    int k;
    for (k = 0; k < 3; k++) {
        const int k1 = (k + 1) % 3, k2 = (k + 2) % 3;
        exp_add_product(e, s * ((double)p[k1] * q[k2]), r[k]);
        exp_add_product(e, -s * ((double)p[k2] * q[k1]), r[k]);
    }
}

/* E_ab = d . (a x b + b x o + o x a), exactly (see the top of the file). */
static void edge_function(const brt_ray *ray, const float *a, const float *b, expansion *e)
{
    e->n = e->overflow = 0;
    add_triple(e, 1.0, a, b, ray->dir);
    add_triple(e, 1.0, b, ray->org, ray->dir);
    add_triple(e, 1.0, ray->org, a, ray->dir);
    exp_compress(e);
}

/* N = det[a,b,c] - det[o,b,c] - det[a,o,c] - det[a,b,o] = (a - o) . n. */
static void plane_numerator(const brt_ray *ray, const float *v[3], expansion *e)
{
    e->n = e->overflow = 0;
    add_triple(e, 1.0, v[0], v[1], v[2]);
    add_triple(e, -1.0, ray->org, v[1], v[2]);
    add_triple(e, -1.0, v[0], ray->org, v[2]);
    add_triple(e, -1.0, v[0], v[1], ray->org);
    exp_compress(e);
}

/* sign(N - x D) * sign(D): the side of ray parameter x on which the plane
** is met (+1: beyond x, i.e. t > x).  x is a finite float. */
static int side_of(const expansion *num, const expansion *den, float x)
{
    expansion e = *num;
    exp_add_scaled(&e, den, -(double)x);
    exp_compress(&e);
    return exp_sign(&e) * exp_sign(den);
}

/* ===================================================================== */
/* Judging one triangle                                                  */
/* ===================================================================== */

typedef enum place {
    INSIDE,        /* through the interior, every edge beyond its band */
    AT_EDGE,       /* through the closed triangle, some edge within its band */
    JUST_OUTSIDE,  /* outside, but only by edges within their bands */
    OUTSIDE,
    PARALLEL       /* D == 0: parallel to the plane, or a degenerate triangle */
} place;
static const char *const place_name[] = {"inside", "at an edge", "just outside", "outside",
                                         "parallel to its plane"};

typedef struct facts {
    uint32_t prim;
    place where;
    int at_vertex;           /* two edges within their bands */
    double edge_ratio;       /* at an edge: the nearest edge's |E| / band;
                             ** just outside: the largest |E| / band of the
                             ** edges it is outside of */
    expansion num, den;      /* N and D, exactly */
    double t, t_bound;       /* N / D rounded to double; the t bound */
    int in_interval;         /* exactly tnear <= t <= tfar */
    int near_limit;          /* t within t_bound of tnear or tfar */
} facts;

static double norm3(const double v[3]) { return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]); }

/* The edge band of edge (a, b), in double (see the top of the file). */
static double edge_band(const brt_ray *ray, const float *a, const float *b)
{
    double A[3], B[3], d[3], Ad[3], Bd[3];
    int k;
    for (k = 0; k < 3; k++) {
        A[k] = (double)a[k] - ray->org[k];
        B[k] = (double)b[k] - ray->org[k];
        d[k] = ray->dir[k];
    }
    ex_cross3(A, d, Ad);
    ex_cross3(B, d, Bd);
    return EDGE_ULPS * FLT_EPSILON * (norm3(A) * norm3(Bd) + norm3(B) * norm3(Ad));
}

/* The t bound at the plane's t (see the top of the file). */
static double t_bound(const brt_ray *ray, const float *v[3], double t, double den)
{
    double edge[3], r = 0.0, l1, l2, d[3];
    int i, k;
    for (i = 0; i < 3; i++) {
        double e[3], w[3];
        for (k = 0; k < 3; k++) {
            e[k] = (double)v[(i + 1) % 3][k] - v[i][k];
            w[k] = (double)v[i][k] - ray->org[k];
            d[k] = ray->dir[k];
        }
        edge[i] = norm3(e);
        r = fmax(r, norm3(w));
    }
    l1 = fmax(edge[0], fmax(edge[1], edge[2]));      /* the two longest edges */
    l2 = edge[0] + edge[1] + edge[2] - l1 - fmin(edge[0], fmin(edge[1], edge[2]));
    return T_ULPS * FLT_EPSILON * (l1 * l2 * (r + fabs(t) * norm3(d)) / fabs(den) + fabs(t));
}

/* Where the ray meets the triangle, from the exact signs of its edge
** functions (oriented by D's sign: +1 means the inner side). */
static void judge_place(const brt_ray *ray, const float *v[3], int den_sign, facts *f)
{
    double nearest = INFINITY, farthest_out = 0.0;
    int i, outside = 0, far_outside = 0, near = 0;
    for (i = 0; i < 3; i++) {
        expansion e;
        const float *a = v[i], *b = v[(i + 1) % 3];
        double ratio;
        int s;
        edge_function(ray, a, b, &e);
        s = exp_sign(&e) * den_sign;
        ratio = s == 0 ? 0.0 : fabs(exp_value(&e)) / edge_band(ray, a, b);
        if (e.overflow) far_outside = 1;
        near += ratio <= 1.0;
        nearest = fmin(nearest, ratio);
        if (s < 0) {
            outside++;
            far_outside |= !(ratio <= 1.0);
            farthest_out = fmax(farthest_out, ratio);
        }
    }
    f->at_vertex = near >= 2;
    if (far_outside) f->where = OUTSIDE;
    else if (outside) f->where = JUST_OUTSIDE;
    else f->where = near ? AT_EDGE : INSIDE;
    f->edge_ratio = f->where == JUST_OUTSIDE ? farthest_out : nearest;
}

/* Everything the referee needs to know about the ray and one triangle. */
static void judge_triangle(const brt_mesh *mesh, const brt_ray *ray, uint32_t prim, facts *f)
{
    const float *v[3];
    int k;
    for (k = 0; k < 3; k++) v[k] = mesh->positions + 3 * (size_t)mesh->indices[3 * (size_t)prim + k];
    memset(f, 0, sizeof *f);
    f->prim = prim;
    add_triple(&f->den, 1.0, v[0], v[1], ray->dir);
    add_triple(&f->den, 1.0, v[1], v[2], ray->dir);
    add_triple(&f->den, 1.0, v[2], v[0], ray->dir);
    exp_compress(&f->den);
    plane_numerator(ray, v, &f->num);
    if (exp_sign(&f->den) == 0 || f->den.overflow || f->num.overflow) {
        f->where = PARALLEL;
        return;
    }
    judge_place(ray, v, exp_sign(&f->den), f);
    f->t = exp_value(&f->num) / exp_value(&f->den);
    f->t_bound = t_bound(ray, v, f->t, exp_value(&f->den));
    f->in_interval = (ray->tnear == -INFINITY
                      || (isfinite(ray->tnear) && side_of(&f->num, &f->den, ray->tnear) >= 0))
                     && (ray->tfar == INFINITY
                         || (isfinite(ray->tfar) && side_of(&f->num, &f->den, ray->tfar) <= 0));
    f->near_limit = fabs(f->t - ray->tnear) <= f->t_bound || fabs(f->t - ray->tfar) <= f->t_bound;
}

/* sign(t_x - t_y), exactly: sign(N_x D_y - N_y D_x) sign(D_x D_y). */
static int compare_t(const facts *x, const facts *y)
{
    expansion p, q;
    exp_multiply(&x->num, &y->den, &p);
    exp_multiply(&y->num, &x->den, &q);
    exp_add_scaled(&p, &q, -1.0);
    exp_compress(&p);
    return exp_sign(&p) * exp_sign(&x->den) * exp_sign(&y->den);
}

/* ===================================================================== */
/* Judging the two answers                                               */
/* ===================================================================== */

/* What is wrong with one side's answer, from worst to best. */
typedef enum fault {
    WRONG,          /* no rounding explains it */
    LEAK,           /* missed a triangle hit at an edge or vertex */
    OUTSIDE_HIT,    /* hit a triangle the ray passes just outside of */
    BOUNDARY,       /* a hit, or a miss of one, within rounding of tnear/tfar */
    ORDER,          /* a farther triangle, nearer than the t bounds can tell */
    RIGHT
} fault;

typedef struct side {
    const brt_hit *hit;
    int hits;
    facts f;         /* of its triangle, when it hits */
    fault own;       /* its own hit: right, or how wrong */
    fault missed;    /* the other side's triangle, if that one is right */
} side;

/* The side's own hit against its triangle's facts. */
static fault judge_own(const brt_ray *ray, side *s)
{
    const facts *f = &s->f;
    const double dt = fabs((double)s->hit->t - f->t);
    if (f->where == PARALLEL) return WRONG;
    if (!(s->hit->t >= ray->tnear && s->hit->t <= ray->tfar)) return WRONG;
    if (!(dt <= f->t_bound) || f->where == OUTSIDE) return WRONG;
    if (!f->in_interval) return f->near_limit ? BOUNDARY : WRONG;
    return f->where == JUST_OUTSIDE ? OUTSIDE_HIT : RIGHT;
}

/* The side did not report triangle g, which the ray does hit (g is the
** other side's, judged right).  Fine when the side's own triangle comes no
** later; otherwise explained by an edge, the interval or the t bounds. */
static fault judge_missed(const side *s, const facts *g)
{
    if (s->hits) {
        const int order = compare_t(g, &s->f);
        if (s->f.prim == g->prim || order >= 0) return RIGHT;
        if (s->f.t - g->t <= s->f.t_bound + g->t_bound) return ORDER;
    }
    if (g->where == AT_EDGE) return LEAK;
    if (g->near_limit) return BOUNDARY;
    return WRONG;
}

/* One side in words: its triangle's exact facts and both judgements. */
static void describe(const side *s, const char *name, char *out, size_t size)
{
    static const char *const fault_name[] = {"wrong", "a leak", "a hit outside", "tnear/tfar",
                                             "within the t bounds", "right"};
    int n = 0;
    if (!s->hits)
        n = snprintf(out, size, "%s: miss", name);
    else
        n = snprintf(out, size, "%s: prim %lu %s%s; exact t %.17g %s [tnear tfar]; record t "
                     "off by %.3g (bound %.3g); own hit %s",
                     name, (unsigned long)s->f.prim, place_name[s->f.where],
                     s->f.at_vertex ? " (vertex)" : "", s->f.t,
                     s->f.in_interval ? "in" : "outside", fabs((double)s->hit->t - s->f.t),
                     s->f.t_bound, fault_name[s->own]);
    if (s->missed != RIGHT && n >= 0 && (size_t)n < size)
        snprintf(out + n, size - (size_t)n, "; missing the other's prim: %s",
                 fault_name[s->missed]);
}

/* The class from both sides' faults: any WRONG is unexplained; otherwise
** the first explanation in the order of the table below. */
static ex_class classify(const side *a, const side *b)
{
    if (a->own == WRONG || b->own == WRONG || a->missed == WRONG || b->missed == WRONG)
        return EX_UNEXPLAINED;
    if (a->hits && b->hits && a->f.prim == b->f.prim) return EX_T_BOUND;
    if (a->missed == LEAK) return EX_LEAK_A;
    if (b->missed == LEAK) return EX_LEAK_B;
    if (a->own == OUTSIDE_HIT) return EX_OUTSIDE_A;
    if (b->own == OUTSIDE_HIT) return EX_OUTSIDE_B;
    if (a->own == BOUNDARY || b->own == BOUNDARY || a->missed == BOUNDARY
        || b->missed == BOUNDARY)
        return EX_BOUNDARY;
    if (a->missed == ORDER || b->missed == ORDER) return EX_NEAR_TIE;
    /* Both hit, both right, neither missed the other's triangle: the same
    ** exact t on two triangles. */
    return a->hits && b->hits ? EX_TIE : EX_UNEXPLAINED;
}

int ex_hits_disagree(const brt_hit *a, const brt_hit *b)
{
    if (a->prim == BRT_NO_PRIM && b->prim == BRT_NO_PRIM) return 0;
    return a->prim != b->prim || a->inst != b->inst || !(a->t == b->t) || !(a->u == b->u) ||
           !(a->v == b->v);
}

ex_class ex_referee(const brt_mesh *mesh, const brt_ray *ray, const brt_hit *a,
                    const brt_hit *b, ex_verdict *out)
{
    side sa, sb, *s[2];
    char da[480], db[480];
    int i;
    s[0] = &sa;
    s[1] = &sb;
    sa.hit = a;
    sb.hit = b;
    out->t_ratio = out->edge_ratio = 0.0;
    if (!brt_ray_valid(ray)) {
        snprintf(out->text, sizeof out->text, "invalid ray (NaN; inf; zero direction or "
                 "tnear > tfar): no tracer may hit it");
        return out->cls = EX_UNEXPLAINED;
    }
    for (i = 0; i < 2; i++) {
        s[i]->hits = s[i]->hit->prim != BRT_NO_PRIM;
        s[i]->own = RIGHT;
        if (s[i]->hits) {
            judge_triangle(mesh, ray, s[i]->hit->prim, &s[i]->f);
            s[i]->own = judge_own(ray, s[i]);
            if (s[i]->f.t_bound > 0.0)
                out->t_ratio = fmax(out->t_ratio,
                                    fabs((double)s[i]->hit->t - s[i]->f.t) / s[i]->f.t_bound);
        }
    }
    for (i = 0; i < 2; i++) {
        const side *other = s[1 - i];
        s[i]->missed = other->hits && other->own == RIGHT ? judge_missed(s[i], &other->f) : RIGHT;
    }
    describe(&sa, "A", da, sizeof da);
    describe(&sb, "B", db, sizeof db);
    snprintf(out->text, sizeof out->text, "%s; %s", da, db);
    out->cls = classify(&sa, &sb);
    /* The edge that explains a leak is the other side's triangle's. */
    out->edge_ratio = out->cls == EX_LEAK_A || out->cls == EX_OUTSIDE_B ? sb.f.edge_ratio
                      : out->cls == EX_LEAK_B || out->cls == EX_OUTSIDE_A ? sa.f.edge_ratio
                      : 0.0;
    return out->cls;
}

/* ===================================================================== */
/* Occlusion records                                                     */
/* ===================================================================== */

/* The padding of a triangle's box for the candidate test: 1e-4 of the
** box's size plus 1e-5 of its largest coordinate, against an edge band of
** EDGE_ULPS FLT_EPSILON ~ 2e-6 of the distances involved, and roundings
** of the slab test itself of a few ulps (1e-7) of the same sizes. */
static double occlusion_pad(const double lo[3], const double hi[3])
{
    double size = 0.0, coord = 0.0;
    int k;
    for (k = 0; k < 3; k++) {
        size = fmax(size, hi[k] - lo[k]);
        coord = fmax(coord, fmax(fabs(lo[k]), fabs(hi[k])));
    }
    return 1e-4 * size + 1e-5 * coord;
}

/* Whether the segment [tnear, tfar] may touch the padded box of triangle
** prim: Kay and Kajiya's slab test in double.  An infinite tnear or tfar
** takes part as it is (no 0 * inf arises: a zero direction component is
** tested against its slab directly). */
static int may_touch(const brt_mesh *mesh, const brt_ray *ray, uint32_t prim)
{
    double lo[3], hi[3], t0 = ray->tnear, t1 = ray->tfar, pad;
    int i, k;
    for (k = 0; k < 3; k++) lo[k] = INFINITY, hi[k] = -INFINITY;
    for (i = 0; i < 3; i++) {
        const float *v = mesh->positions + 3 * (size_t)mesh->indices[3 * (size_t)prim + i];
        for (k = 0; k < 3; k++) lo[k] = fmin(lo[k], v[k]), hi[k] = fmax(hi[k], v[k]);
    }
    pad = occlusion_pad(lo, hi);
    for (k = 0; k < 3; k++) {
        const double o = ray->org[k], d = ray->dir[k], a = lo[k] - pad, b = hi[k] + pad;
        if (d == 0.0) {
            if (o < a || o > b) return 0;
        } else {
            const double ta = (a - o) / d, tb = (b - o) / d;
            t0 = fmax(t0, fmin(ta, tb));
            t1 = fmin(t1, fmax(ta, tb));
        }
    }
    return t0 <= t1;
}

/* What the candidates show, for the class: the exact hits (inside or on
** an edge, tnear <= t <= tfar) and the triangles only rounding can hit. */
typedef struct occlusion_facts {
    unsigned long candidates;
    unsigned long inside, inside_limit; /* exact hits inside: well inside the
                                        ** segment, or within a t bound of
                                        ** tnear or tfar */
    unsigned long at_edge;              /* exact hits at an edge or vertex */
    unsigned long just_outside;         /* in [tnear, tfar], just outside */
    unsigned long near_limit;           /* just beyond tnear or tfar */
    uint32_t example;                   /* the prim that decided the class */
    double t, edge_ratio, limit_ratio;  /* its exact t, |E| / band, and
                                        ** distance to tnear/tfar / t bound */
} occlusion_facts;

static double limit_ratio(const brt_ray *ray, const facts *f)
{
    return fmin(fabs(f->t - ray->tnear), fabs(f->t - ray->tfar)) / f->t_bound;
}

/* Judges every candidate; remembers one prim of the most telling kind. */
static void judge_candidates(const brt_mesh *mesh, const brt_ray *ray, occlusion_facts *o)
{
    /* Rank of each kind in the explanation: a hit well inside decides
    ** everything, an edge hit explains a leak, ... */
    int best = 0;
    uint32_t prim;
    memset(o, 0, sizeof *o);
    o->example = BRT_NO_PRIM;
    for (prim = 0; prim < mesh->triangle_count; prim++) {
        facts f;
        int rank = 0;
        if (!may_touch(mesh, ray, prim)) continue;
        o->candidates++;
        judge_triangle(mesh, ray, prim, &f);
        if (f.where == PARALLEL || f.where == OUTSIDE) continue;
        if (f.in_interval && f.where == INSIDE && !f.near_limit) o->inside++, rank = 6;
        else if (f.in_interval && f.where == AT_EDGE) o->at_edge++, rank = 5;
        else if (f.in_interval && f.where == INSIDE) o->inside_limit++, rank = 4;
        else if (f.in_interval) o->just_outside++, rank = 3;
        else if (f.near_limit) o->near_limit++, rank = 2;
        if (rank > best) {
            best = rank;
            o->example = prim;
            o->t = f.t;
            o->edge_ratio = f.edge_ratio;
            o->limit_ratio = limit_ratio(ray, &f);
        }
    }
}

/* The class of an occlusion disagreement: zero is the side saying 0
** (0 for A, 1 for B). */
static ex_class classify_occlusion(const occlusion_facts *o, int zero)
{
    if (o->inside) return EX_UNEXPLAINED;                   /* 0 is wrong */
    if (o->at_edge) return zero == 0 ? EX_LEAK_A : EX_LEAK_B;
    if (o->inside_limit) return EX_BOUNDARY;
    if (o->just_outside) return zero == 0 ? EX_OUTSIDE_B : EX_OUTSIDE_A;
    if (o->near_limit) return EX_BOUNDARY;
    return EX_UNEXPLAINED;                                   /* 1 is wrong */
}

ex_class ex_referee_occlusion(const brt_mesh *mesh, const brt_ray *ray, int a, int b,
                              ex_verdict *out)
{
    occlusion_facts o;
    out->t_ratio = out->edge_ratio = 0.0;
    if (!brt_ray_valid(ray)) {
        snprintf(out->text, sizeof out->text, "invalid ray (NaN; inf; zero direction or "
                 "tnear > tfar): no tracer may report it occluded");
        return out->cls = EX_UNEXPLAINED;
    }
    judge_candidates(mesh, ray, &o);
    out->cls = classify_occlusion(&o, a == 0 ? 0 : 1);
    if (out->cls == EX_LEAK_A || out->cls == EX_LEAK_B || out->cls == EX_OUTSIDE_A
        || out->cls == EX_OUTSIDE_B)
        out->edge_ratio = o.edge_ratio;
    if (out->cls == EX_BOUNDARY) out->t_ratio = o.limit_ratio;
    if (o.example == BRT_NO_PRIM)
        snprintf(out->text, sizeof out->text, "A: %d; B: %d; %lu candidate triangles; none hit "
                 "or within rounding of a hit", a, b, o.candidates);
    else
        snprintf(out->text, sizeof out->text, "A: %d; B: %d; %lu candidate triangles; exact "
                 "hits: %lu inside %lu inside near tnear/tfar %lu at an edge; just outside "
                 "%lu; just beyond tnear/tfar %lu; deciding prim %lu at exact t %.17g "
                 "(|E| / band %.3g; distance to tnear/tfar / t bound %.3g)",
                 a, b, o.candidates, o.inside, o.inside_limit, o.at_edge, o.just_outside,
                 o.near_limit, (unsigned long)o.example, o.t, o.edge_ratio, o.limit_ratio);
    return out->cls;
}

/* ===================================================================== */
/* Instanced hits                                                        */
/* ===================================================================== */

/* A stream as a mesh: three vertices per triangle, in order. */
static brt_result mesh_of(brt_result (*run)(const void *, uint32_t, brt_triangle_fn, void *, brt_error *),
                          const void *user, uint32_t id, brt_mesh *mesh, brt_error *err)
{
    ex_corners g = {NULL, 0, 0};
    brt_result r = run(user, id, ex_corners_append, &g, err);
    size_t i;
    memset(mesh, 0, sizeof *mesh);
    if (r != BRT_OK) {
        free(g.corners);
        return r;
    }
    mesh->positions = g.corners;
    mesh->indices = malloc(3 * g.count * sizeof *mesh->indices + 1);
    if (!mesh->indices) return brt_fail(err, BRT_ENOMEM, "out of memory for the referee's triangles");
    for (i = 0; i < 3 * g.count; i++) mesh->indices[i] = (uint32_t)i;
    mesh->vertex_count = (uint32_t)(3 * g.count);
    mesh->triangle_count = (uint32_t)g.count;
    return BRT_OK;
}

static brt_result run_world(const void *user, uint32_t id, brt_triangle_fn emit, void *emit_user,
                            brt_error *err)
{
    const brt_scene_source *s = user;
    (void)id;
    return s->world.run ? s->world.run(s->world.user, emit, emit_user, err) : BRT_OK;
}

static brt_result run_prototype(const void *user, uint32_t id, brt_triangle_fn emit,
                                void *emit_user, brt_error *err)
{
    const brt_scene_source *s = user;
    return s->prototype(s->user, id, emit, emit_user, err);
}

static brt_result gather_instances(void *user, const brt_instance *in, uint32_t count,
                                   uint32_t first, brt_error *err)
{
    ex_instanced_mesh *m = user;
    size_t cap = m->instance_count;
    (void)first;
    if (!(m->instances = brt_grow(m->instances, &cap, (size_t)m->instance_count + count,
                                  sizeof *m->instances)))
        return brt_fail(err, BRT_ENOMEM, "out of memory for the referee's instances");
    memcpy(m->instances + m->instance_count, in, count * sizeof *in);
    m->instance_count += count;
    return BRT_OK;
}

brt_result ex_instanced_mesh_load(const brt_scene_source *source, ex_instanced_mesh *m,
                                  brt_error *err)
{
    brt_result r;
    uint32_t p;
    memset(m, 0, sizeof *m);
    r = mesh_of(run_world, source, 0, &m->world, err);
    m->prototypes = calloc((size_t)source->prototype_count + 1, sizeof *m->prototypes);
    if (r == BRT_OK && !m->prototypes) r = brt_fail(err, BRT_ENOMEM, "out of memory");
    for (p = 0; p < source->prototype_count && r == BRT_OK; p++, m->prototype_count++)
        r = mesh_of(run_prototype, source, p, &m->prototypes[p], err);
    if (r == BRT_OK && source->instances) r = source->instances(source->user, gather_instances, m, err);
    if (r != BRT_OK) ex_instanced_mesh_free(m);
    return r;
}

void ex_instanced_mesh_free(ex_instanced_mesh *m)
{
    uint32_t p;
    brt_mesh_free(&m->world);
    for (p = 0; m->prototypes && p < m->prototype_count; p++) brt_mesh_free(&m->prototypes[p]);
    free(m->prototypes);
    free(m->instances);
    memset(m, 0, sizeof *m);
}

/* A record's triangle in world space (double) and its margin. */
typedef struct world_triangle {
    double v[3][3];
    double margin;
} world_triangle;

static int world_triangle_of(const ex_instanced_mesh *m, const brt_ray *ray, const brt_hit *h,
                             world_triangle *w)
{
    const brt_mesh *mesh = &m->world;
    const brt_instance *in = NULL;
    int j, a;
    w->margin = 0.0;
    if (h->inst != BRT_NO_INST) {
        brt_instance_frame f;
        float olo[3], ohi[3], lo[3], hi[3], radius, centre[3];
        if (h->inst >= m->instance_count) return 0;
        in = &m->instances[h->inst];
        if (in->prototype >= m->prototype_count ||
            brt_instance_frame_init(in, h->inst, &f, NULL) != BRT_OK)
            return 0;
        mesh = &m->prototypes[in->prototype];
        brt_mesh_bounds(mesh, olo, ohi);
        brt_instance_bounds(in, &f, olo, ohi, lo, hi, &radius);
        for (a = 0; a < 3; a++) centre[a] = in->xform[4 * a + 3];
        w->margin = brt_instance_margin(f.condition, radius, centre, ray);
    }
    if (h->prim >= mesh->triangle_count) return 0;
    for (j = 0; j < 3; j++) {
        const float *v = mesh->positions + 3 * (size_t)mesh->indices[3 * (size_t)h->prim + j];
        for (a = 0; a < 3; a++)
            w->v[j][a] = in ? (double)in->xform[4 * a] * v[0] + (double)in->xform[4 * a + 1] * v[1] +
                                  (double)in->xform[4 * a + 2] * v[2] + in->xform[4 * a + 3]
                            : v[a];
    }
    return 1;
}

static double dot3(const double a[3], const double b[3]) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

static void sub3(const double a[3], const double b[3], double c[3])
{
    int k;
    for (k = 0; k < 3; k++) c[k] = a[k] - b[k];
}

/* Distance from p to segment ab. */
static double segment_distance(const double p[3], const double a[3], const double b[3])
{
    double ab[3], ap[3], q[3], s;
    int k;
    sub3(b, a, ab);
    sub3(p, a, ap);
    s = dot3(ab, ab) > 0 ? fmin(1.0, fmax(0.0, dot3(ap, ab) / dot3(ab, ab))) : 0.0;
    for (k = 0; k < 3; k++) q[k] = a[k] + s * ab[k] - p[k];
    return sqrt(dot3(q, q));
}

/* Distance from p to the triangle (Ericson's region test, plainly: the
** plane when p projects inside, else the nearest edge); *edge gets the
** distance to the nearest edge, *inside whether p projects inside. */
static double triangle_distance(const world_triangle *w, const double p[3], double *edge, int *inside)
{
    double e1[3], e2[3], n[3], d[3], len;
    int j, in = 1;
    sub3(w->v[1], w->v[0], e1);
    sub3(w->v[2], w->v[0], e2);
    ex_cross3(e1, e2, n);
    len = sqrt(dot3(n, n));
    *edge = INFINITY;
    for (j = 0; j < 3; j++) *edge = fmin(*edge, segment_distance(p, w->v[j], w->v[(j + 1) % 3]));
    if (len == 0) { *inside = 0; return *edge; }
    for (j = 0; j < 3; j++) {
        double ej[3], pj[3], c[3];
        sub3(w->v[(j + 1) % 3], w->v[j], ej);
        sub3(p, w->v[j], pj);
        ex_cross3(ej, pj, c);
        if (dot3(c, n) < 0) in = 0;
    }
    *inside = in;
    sub3(p, w->v[0], d);
    return in ? fabs(dot3(d, n)) / len : *edge;
}

static void point_at(const brt_ray *ray, double t, double p[3])
{
    int k;
    for (k = 0; k < 3; k++) p[k] = (double)ray->org[k] + t * ray->dir[k];
}

/* The exact world ray meets the plane of w inside it, farther than band
** from every edge: a miss there is not the transform's. */
static int ray_crosses_interior(const brt_ray *ray, const world_triangle *w, double band)
{
    double e1[3], e2[3], n[3], o[3], d[3], w0[3], t, p[3], edge;
    int k, inside;
    sub3(w->v[1], w->v[0], e1);
    sub3(w->v[2], w->v[0], e2);
    ex_cross3(e1, e2, n);
    for (k = 0; k < 3; k++) { o[k] = ray->org[k]; d[k] = ray->dir[k]; }
    if (dot3(n, d) == 0) return 0;
    sub3(w->v[0], o, w0);
    t = dot3(w0, n) / dot3(n, d);
    if (!(t >= ray->tnear && t <= ray->tfar)) return 0;
    point_at(ray, t, p);
    triangle_distance(w, p, &edge, &inside);
    return inside && edge > band;
}

/* |cos| between the ray and the triangle's normal. */
static double incidence(const brt_ray *ray, const world_triangle *w)
{
    double e1[3], e2[3], n[3], d[3];
    int k;
    sub3(w->v[1], w->v[0], e1);
    sub3(w->v[2], w->v[0], e2);
    ex_cross3(e1, e2, n);
    for (k = 0; k < 3; k++) d[k] = ray->dir[k];
    if (dot3(n, n) == 0 || dot3(d, d) == 0) return 0;
    return fabs(dot3(n, d)) / sqrt(dot3(n, n) * dot3(d, d));
}

/* A record judged alone in its own space (against a miss): right, or a
** hit just outside an edge within rounding (ex_referee's classes). */
static int own_space_explains(const ex_instanced_mesh *m, const brt_ray *ray, const brt_hit *h)
{
    brt_hit alone = *h, miss;
    brt_ray object_ray = *ray;
    const brt_mesh *mesh = &m->world;
    ex_verdict v;
    ex_class c;
    brt_hit_clear(&miss);
    if (h->inst != BRT_NO_INST) {
        brt_instance_frame f;
        if (brt_instance_frame_init(&m->instances[h->inst], h->inst, &f, NULL) != BRT_OK) return 0;
        brt_instance_ray(&f, ray, &object_ray);
        mesh = &m->prototypes[m->instances[h->inst].prototype];
    }
    alone.inst = BRT_NO_INST;
    c = ex_referee(mesh, &object_ray, &alone, &miss, &v);
    return c == EX_LEAK_B || c == EX_OUTSIDE_A || c == EX_BOUNDARY;
}

static ex_class unexplained(ex_verdict *out, const char *why)
{
    snprintf(out->text, sizeof out->text, "instanced: %s", why);
    return out->cls = EX_UNEXPLAINED;
}

/* The transform class: see the header. */
static ex_class transform_class(const ex_instanced_mesh *m, const brt_ray *ray, const brt_hit *h[2],
                                ex_verdict *out)
{
    world_triangle w[2];
    int hits[2], i;
    const double dir = sqrt((double)ray->dir[0] * ray->dir[0] + (double)ray->dir[1] * ray->dir[1] +
                            (double)ray->dir[2] * ray->dir[2]);
    for (i = 0; i < 2; i++) {
        double p[3], edge, dist;
        int inside;
        double rounding;
        hits[i] = h[i]->prim != BRT_NO_PRIM;
        if (!hits[i]) continue;
        /* The record's own rounding: t and the point it names, in float. */
        point_at(ray, 0.0, p);
        rounding = 0x1p-20 * (sqrt(dot3(p, p)) + fabs((double)h[i]->t) * dir);
        if (!world_triangle_of(m, ray, h[i], &w[i]))
            return unexplained(out, "a record names an instance or prim the scene lacks");
        point_at(ray, h[i]->t, p);
        dist = triangle_distance(&w[i], p, &edge, &inside);
        out->t_ratio = fmax(out->t_ratio, w[i].margin > 0 ? dist / (2 * w[i].margin) : INFINITY);
        if (!(dist <= 2 * w[i].margin + rounding) && !own_space_explains(m, ray, h[i]))
            return unexplained(out, "a hit farther from its triangle than the transform's bound");
    }
    for (i = 0; i < 2; i++) {
        if (hits[i] || !hits[1 - i]) continue;
        if (ray_crosses_interior(ray, &w[1 - i], 2 * w[1 - i].margin))
            return unexplained(out, "a miss where the ray crosses a triangle's interior");
    }
    if (hits[0] && hits[1]) {
        /* Two hits: equal within the bound, or the farther record passed
        ** the nearer one's triangle within the bound of an edge. */
        const int near = h[0]->t <= h[1]->t ? 0 : 1;
        const double c = fmax(incidence(ray, &w[near]), 1e-3);
        const double gap = fabs((double)h[0]->t - h[1]->t) * dir, bound = 2 * (w[0].margin + w[1].margin) / c;
        if (!(gap <= bound) && ray_crosses_interior(ray, &w[near], 2 * w[near].margin))
            return unexplained(out, "a farther hit where the ray crosses a nearer triangle's interior");
    }
    snprintf(out->text, sizeof out->text, "instanced: both records within the rounding of the "
             "ray's transform into object space (%.3g of its bound)", out->t_ratio);
    return out->cls = EX_TRANSFORM;
}

ex_class ex_referee_instanced(const ex_instanced_mesh *m, const brt_ray *ray, const brt_hit *a,
                              const brt_hit *b, ex_verdict *out)
{
    const brt_hit *h[2];
    uint32_t space = a->prim != BRT_NO_PRIM ? a->inst : b->inst;
    int one_space = (a->prim == BRT_NO_PRIM || b->prim == BRT_NO_PRIM) || a->inst == b->inst;
    h[0] = a;
    h[1] = b;
    if (one_space && (space == BRT_NO_INST ||
                      (space < m->instance_count && m->instances[space].prototype < m->prototype_count))) {
        brt_hit sa = *a, sb = *b;
        brt_ray object_ray = *ray;
        const brt_mesh *mesh = &m->world;
        brt_instance_frame f;
        if (space != BRT_NO_INST) {
            if (brt_instance_frame_init(&m->instances[space], space, &f, NULL) != BRT_OK)
                return out->cls = EX_UNEXPLAINED;
            brt_instance_ray(&f, ray, &object_ray);
            mesh = &m->prototypes[m->instances[space].prototype];
        }
        sa.inst = sb.inst = BRT_NO_INST;
        if (ex_referee(mesh, &object_ray, &sa, &sb, out) != EX_UNEXPLAINED || space == BRT_NO_INST)
            return out->cls;
    }
    out->t_ratio = out->edge_ratio = 0.0;
    return transform_class(m, ray, h, out);
}
