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

/* Fills mesh (malloc'd arrays; free with brt_mesh_free) with the named
** scene.  The same name, scale and seed give the same bytes.  BRT_EARG for
** an unknown name or a scale outside (0, EX_SCENE_MAX_SCALE]; BRT_ENOMEM
** when the arrays cannot be allocated.  Only random numbers of
** brt_random_u64/brt_random_float are used, so the result depends on the
** seed and on libm's sin/cos/pow, nothing else. */
brt_result ex_scene_generate(const char *name, double scale, uint64_t seed,
                             brt_mesh *mesh, brt_error *err);

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
