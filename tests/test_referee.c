/*
** tests/test_referee.c -- the referee of hitdiff (examples/referee.c) on
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
#include "../examples/referee.h"

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
    h.inst = BRT_NO_INST;   /* a world triangle: brt_hits_write refuses instances */
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
    test_run("referee: occlusion records: leak, outside, tfar, fabricated 0 and 1",
             test_occlusion_referee);
    test_run("referee: hitdiff --mesh table, exit status and --explain",
             test_hitdiff_referee);
    test_run("referee: hitdiff --occlusion --mesh table, exit status and --explain",
             test_hitdiff_occlusion_referee);
    test_run("referee: hitdiff --mesh rejects bad input in one line", test_hitdiff_bad_input);
}
