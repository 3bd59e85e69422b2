/*
** examples/lib/referee.h -- hitdiff's referee: for a ray on which two hit files
** disagree, decides with exact arithmetic which side is right, or that both
** are, and names the reason (examples/lib/referee.c explains how).  Shared by
** build/hitdiff and the tests (tests/test_referee.c, tests/test_embree.c).
**
** The referee judges closest-hit records (brt_hit), and occlusion records
** (ex_referee_occlusion).  It looks only at the
** triangles the two records name: it never traces the ray itself, so a
** side that misses a triangle neither side reports is not caught (a
** disagreement always names at least one triangle, so it is refereed).
*/
#ifndef BRT_EXAMPLES_REFEREE_H
#define BRT_EXAMPLES_REFEREE_H

#include "batchrt.h"

#include <stddef.h>
#include <stdint.h>

/* The classes of a disagreement, in the order of hitdiff's table.  "A" and
** "B" are the two records of the ray (hitdiff's first and second file). */
typedef enum ex_class {
    EX_TIE,          /* both right: two triangles hit at exactly the same t */
    EX_NEAR_TIE,     /* two triangles hit, their exact t closer than the t
                     ** bound: which is closer is rounding */
    EX_T_BOUND,      /* the same triangle, each t within the bound for this
                     ** ray's conditioning */
    EX_LEAK_A,       /* A passes through an edge or vertex of a triangle the
                     ** ray hits (B's): A reports a miss or a farther hit */
    EX_LEAK_B,
    EX_OUTSIDE_A,    /* A hits a triangle the ray passes just outside of,
                     ** within rounding of an edge or vertex */
    EX_OUTSIDE_B,
    EX_BOUNDARY,     /* the hit's exact t is within rounding of tnear or tfar */
    EX_TRANSFORM,    /* instances: both records within the rounding of the ray's
                     ** transform into object space (ex_referee_instanced) */
    EX_UNEXPLAINED,
    EX_CLASSES
} ex_class;

extern const char *const ex_class_id[EX_CLASSES];     /* "tie", "leak_a", ... (CSV) */
extern const char *const ex_class_label[EX_CLASSES];  /* table rows */

/* Nonzero when the two records of one ray disagree: a different instance
** or prim, hit against miss, or a different t, u or v (two misses always
** agree). */
int ex_hits_disagree(const brt_hit *a, const brt_hit *b);

/* The referee's answer for one ray. */
typedef struct ex_verdict {
    ex_class cls;
    double t_ratio;      /* the largest |record t - exact t| / t bound of the
                         ** records that hit a triangle (0 when none does) */
    double edge_ratio;   /* leaks and hits just outside: the |E| / edge band
                         ** of the edge that explains it (0 in other classes) */
    char text[1024];     /* the exact verdict in words, without commas or quotes */
} ex_verdict;

/* Referees one ray on which a and b disagree, into *out; returns out->cls.
** Every prim must be BRT_NO_PRIM or below mesh->triangle_count (hitdiff
** checks the files first). */
ex_class ex_referee(const brt_mesh *mesh, const brt_ray *ray, const brt_hit *a,
                    const brt_hit *b, ex_verdict *out);

/* Referees one ray on which two occlusion records a and b (0 clear, 1
** occluded) disagree, into *out; returns out->cls.  The candidates are
** found by brute force over the mesh (referee.c, OCCLUSION): O(triangles)
** per call.  The classes keep their meaning: a leak is the side saying 0
** when the only exact hits are at an edge or vertex; a hit just outside is
** the side saying 1 when no triangle is hit exactly but one is missed by
** less than an edge band; t_ratio is the boundary's distance to tnear or
** tfar / t bound. */
ex_class ex_referee_occlusion(const brt_mesh *mesh, const brt_ray *ray, int a, int b,
                              ex_verdict *out);

/* An instanced scene for the referee (a pbrt file's): the world
** triangles and each prototype as meshes, numbered as hit files number
** them, and the instances. */
typedef struct ex_instanced_mesh {
    brt_mesh world;
    brt_mesh *prototypes;
    uint32_t prototype_count;
    brt_instance *instances;
    uint32_t instance_count;
} ex_instanced_mesh;

brt_result ex_instanced_mesh_load(const brt_scene_source *source, ex_instanced_mesh *out,
                                  brt_error *err);
void ex_instanced_mesh_free(ex_instanced_mesh *m);

/* Referees one ray of an instanced scene (records naming instances).  When
** every record that hits lies in one space -- the world, or one instance
** -- ex_referee judges them exactly there, the ray carried into the
** instance by brt_instance_ray (batchrt's transform).  Otherwise, or when
** that leaves them unexplained, EX_TRANSFORM when each hit lies within
** 2 d of its world triangle (d: the instance's margin, batchrt.h
** brt_instance_margin, 0 for the world), a miss faces a hit that the
** exact world ray takes within 2 d of an edge, and two hits are closer in
** t than 2 (d_a + d_b) / |cos| along the ray (cos between the ray and the
** nearer triangle): differences another transform of the same ray (an
** Embree build's, in float) can make.  t_ratio: the largest of these
** distances over its bound. */
ex_class ex_referee_instanced(const ex_instanced_mesh *m, const brt_ray *ray, const brt_hit *a,
                              const brt_hit *b, ex_verdict *out);

#endif
