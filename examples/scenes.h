/*
** examples/scenes.h -- the built-in procedural scenes (no download):
** deterministic from a seed, sized by a scale factor.  They stand in for
** the three test scenes of Molenaar and Eisemann (2020):
**
**   crown      one heavily subdivided closed ornate object (a band with
**              scallops, arches, spikes, gems, pearls, an orb and a cross);
**              every edge is shared by exactly two triangles of opposite
**              orientation, normals point outwards.
**   landscape  a terrain heightfield with forests of conifers and leafy
**              trees and groups of rocks baked into world space: open
**              geometry, much empty space inside the boxes of clusters.
**   island     islands in a sea (the sea is two large triangles at y = 0;
**              the islands' shores go below it) with dense vegetation:
**              palms, bushes and grass tufts.
**
** Scale 1 is about 100 thousand triangles; the count grows in proportion
** to the scale (scale 500: about 50 million).  y is up; units are metres
** for landscape and island, the crown is about 2.2 units wide.
*/
#ifndef BRT_EXAMPLES_SCENES_H
#define BRT_EXAMPLES_SCENES_H

#include "batchrt.h"

#define EX_SCENE_MAX_SCALE 10000.0   /* about a billion triangles */

/* Changed whenever a generator changes its triangles: it is part of a
** built-in scene's stamp (ex_scene_stamp), so scene files made by an
** older generator are rebuilt, never reused. */
#define EX_SCENE_GENERATOR_VERSION 3   /* 2: closed island land masses, closed terrain; 3: closing triangles local */

/* A built-in scene: name, scale and seed determine its triangles. */
typedef struct ex_scene_recipe {
    const char *name;
    double scale;
    uint64_t seed;
} ex_scene_recipe;

/* Fills mesh (malloc'd arrays; free with brt_mesh_free) with the named
** scene: the collector of ex_scene_write, for --direct and the tests.  The
** same name, scale and seed give the same bytes.  BRT_EARG for an unknown
** name or a scale outside (0, EX_SCENE_MAX_SCALE]; BRT_ENOMEM when the
** arrays cannot be allocated.  Only random numbers of
** brt_random_u64/brt_random_float are used, so the result depends on the
** seed and on libm's sin/cos/pow, nothing else. */
brt_result ex_scene_generate(const char *name, double scale, uint64_t seed,
                             brt_mesh *mesh, brt_error *err);

/* An indexed mesh as it is made: vertices (3 floats each) and triangles
** (3 vertex numbers each, counted from 0 over the whole scene) in the
** order of ex_scene_generate's arrays, in batches.  A callback returns
** BRT_OK to go on; anything else stops the scene, which returns it (the
** callback wrote err). */
typedef struct ex_mesh_sink {
    brt_result (*vertices)(void *user, const float *xyz, uint32_t count, brt_error *err);
    brt_result (*triangles)(void *user, const uint32_t *abc, uint32_t count, brt_error *err);
    void *user;
} ex_mesh_sink;

/* The scene to a sink, holding one object (or three rows of a large grid)
** at a time, never the scene.  Errors as ex_scene_generate. */
brt_result ex_scene_write(const ex_scene_recipe *recipe, const ex_mesh_sink *sink,
                          brt_error *err);

/* The scene's vertex and triangle counts, without making its geometry
** (placements only: a few per cent of ex_scene_write's time). */
brt_result ex_scene_count(const ex_scene_recipe *recipe, uint64_t *vertices,
                          uint64_t *triangles, brt_error *err);

/* The scene as a triangle stream (brt_triangle_fn chunks: corners of
** ex_scene_generate's triangles, in its order), in the same bounded memory
** as ex_scene_write; and as a source for brt_scene_build_stream (recipe
** must outlive the source).  Every run yields the same chunks. */
brt_result ex_scene_stream(const ex_scene_recipe *recipe, brt_triangle_fn emit,
                           void *emit_user, brt_error *err);
void ex_scene_source(const ex_scene_recipe *recipe, brt_triangle_source *source);

/* A stamp for a built-in scene's scene file (brt_scene_build_stream): a
** checksum of the recipe and EX_SCENE_GENERATOR_VERSION, so a matching
** scene file is reused without making the scene at all. */
uint64_t ex_scene_stamp(const ex_scene_recipe *recipe);

/* The built-in names, NULL-terminated. */
const char *const *ex_scene_names(void);

/* Nonzero when name is a built-in scene. */
int ex_scene_is_builtin(const char *name);

/* A good default view of a scene with the given bounds: the crown from the
** front and a little above, the landscape from a low oblique angle across
** its length (so rays cross many batching points), the islands from high
** above their sea.  Any other name gets a view from +z and a little above
** that shows the whole box. */
void ex_scene_camera(const char *name, const float bmin[3],
                     const float bmax[3], float eye[3], float target[3],
                     float *fov_degrees);

#endif
