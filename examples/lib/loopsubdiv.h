/*
** examples/lib/loopsubdiv.h -- Loop subdivision surfaces as pbrt-v4 refines
** its Shape "loopsubdiv" into triangles when it loads a scene: the
** triangles pbrt-v4 intersects, vertex for vertex and in its order.
** It follows Loop, "Smooth Subdivision Surfaces Based on Triangles"
** (M.S. thesis, University of Utah, 1987) as pbrt-v4 implements it in
** src/pbrt/util/loopsubdiv.cpp (LoopSubdivide; pbrt-v3's book, 4.6 in
** the online edition, explains the same code).
**
** THE REFINEMENT.  The control mesh (P, indices) is subdivided `levels`
** times (none when levels <= 0); each level
**   - moves every old ("even") vertex: interior, Loop's one-ring rule
**     (1 - n beta) p + beta * (sum of its n neighbours), beta = 1/16 for
**     valence 6, 3/16 for valence 3, else 3 / (8 n); on a boundary,
**     3/4 p + 1/8 (its two boundary neighbours);
**   - adds a new ("odd") vertex on every edge: interior, 3/8 of each
**     end + 1/8 of the two opposite corners; boundary, the midpoint;
**   - splits every triangle into four.
** Then every vertex is pushed to its point on the limit surface: interior,
** the one-ring rule with gamma = 1 / (n + 3 / (8 beta)) in place of beta;
** boundary, 3/5 p + 1/5 (its two boundary neighbours).  Levels 0 is
** therefore the control mesh with its vertices on the limit surface.
** Arithmetic is in float, operation for operation as pbrt-v4 writes it
** (its default build, Float = float), summing each one-ring in pbrt's
** order: from the vertex's "start face" around.  A compiler that fuses a
** multiply and add (batchrt builds with -ffp-contract=off; pbrt's build
** may not) can differ from it in the last bit.
**
** THE ORDER (pbrt-v4's output TriangleMesh).  Vertices: the control
** vertices first, in P's order, then each level's edge vertices appended
** in the order their edges are first met (faces in order, edges v0v1,
** v1v2, v2v0).  Triangles: each level replaces face (v0, v1, v2), in
** place, by its four children, in this order, m01 being the edge vertex
** of v0v1:
**     (v0, m01, m20), (m01, v1, m12), (m20, m12, v2), (m01, m12, m20)
** so control face i's triangles are numbers i * 4^levels to
** (i + 1) * 4^levels - 1, each oriented as its face.
**
** WHAT IS REFUSED (BRT_EPARSE, one line; the caller names the file and
** line).  pbrt-v4's pointer walks around a vertex assume a manifold,
** consistently oriented mesh; on other input it dereferences a null face
** (an unused vertex), stops with "Basic logic error" (a corner repeated
** in a face), can walk forever (two faces running an edge the same way),
** or silently keeps the first two faces of an edge with more and only one
** fan of faces at a vertex where several meet at a point.  All of these
** are refused here: an index out of range, a face repeating a corner, an
** edge in more than two faces, an edge two faces run the same way, a
** vertex in no face, a vertex whose faces form more than one fan; and a
** refinement beyond EX_LOOP_MAX_TRIANGLES (2^20) triangles.
**
** MEMORY.  The mesh is held whole while refined: the control mesh and at
** most two levels at once (the one read and the one made): 24 bytes a
** face, 20 a vertex (about one vertex per two faces), 12 per face of the
** level read for its edge vertices; then the output, 12 bytes a vertex
** and 12 a triangle.
*/
#ifndef BRT_EXAMPLES_LOOPSUBDIV_H
#define BRT_EXAMPLES_LOOPSUBDIV_H

#include "batchrt.h"

/* The refined mesh: positions on the limit surface (3 floats a vertex)
** and triangles (3 indices each), in the order above. */
typedef struct ex_loop_mesh {
    float *p;
    uint32_t *indices;
    uint32_t vertex_count, triangle_count;
} ex_loop_mesh;

/* The most triangles a refinement may make: 2^20.  The mesh is held whole
** while refined (MEMORY above), so the bound keeps a shape of a few bytes
** ("levels" 20) from asking for gigabytes; it is far above what published
** scenes refine to, and a fuzzed file stays within the fuzzer's memory and
** time (make fuzz-smoke builds them with a smaller one). */
#ifndef EX_LOOP_MAX_TRIANGLES
#define EX_LOOP_MAX_TRIANGLES (1u << 20)
#endif

/* faces * 4^levels (faces for levels <= 0), UINT64_MAX past 2^63. */
uint64_t ex_loop_triangle_count(uint64_t faces, int levels);

/* The topology checks above, without refining (indices: 3 per face). */
brt_result ex_loop_check(const uint32_t *indices, uint32_t face_count, uint32_t vertex_count,
                         brt_error *err);

/* Refines the control mesh (p: 3 floats a vertex, object space; indices: 3
** per face) levels times and pushes it to the limit surface, into *out
** (free with ex_loop_free; zeroed on error). */
brt_result ex_loop_subdivide(const float *p, uint32_t vertex_count, const uint32_t *indices,
                             uint32_t face_count, int levels, ex_loop_mesh *out, brt_error *err);

void ex_loop_free(ex_loop_mesh *mesh);   /* NULL: nothing, as free(NULL) */

#endif
