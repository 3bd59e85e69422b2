/*
** examples/lib/scenes.h -- the built-in procedural scenes (no download):
** deterministic from a seed, sized by a scale factor.  They stand in for
** the three test scenes of Molenaar and Eisemann (2020):
**
**   crown      one heavily subdivided closed ornate object (a band with
**              scallops, arches, spikes, gems, pearls, an orb and a cross);
**              every edge is shared by exactly two triangles of opposite
**              orientation, normals point outwards.
**   landscape  a terrain heightfield with forests, meadows and groups of
**              rocks; island: islands in a sea (two large triangles at
**              y = 0; the shores go below it) with palms, bushes and
**              grass.  One generation each: the instanced scenes below,
**              which render draws; as a mesh (ex_scene_generate, _write,
**              _stream) baked, every instance's prototype in world space.
**
** The crown at scale 1 is about 100 thousand triangles, in proportion to
** the scale (scale 500: about 50 million); the landscape and the island
** baked have their instanced triangles (ex_instanced_counts: about 6.5 M
** and 4 M at scale 1).  y is up; units are metres for landscape and
** island, the crown is about 2.2 units wide.
*/
#ifndef BRT_EXAMPLES_SCENES_H
#define BRT_EXAMPLES_SCENES_H

#include "batchrt.h"

#define EX_SCENE_MAX_SCALE 10000.0   /* about a billion triangles */

/* Changed whenever a generator changes its triangles: it is part of a
** built-in scene's stamp (ex_scene_stamp), so scene files made by an
** older generator are rebuilt, never reused. */
#define EX_SCENE_GENERATOR_VERSION 4   /* 2: closed island land masses, closed terrain; 3: closing triangles local; 4: landscape and island baked from the instanced scenes */

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

/* ===================================================================== */
/* Instanced scenes                                                      */
/* ===================================================================== */
/*
** The landscape and the island as the paper has them: world triangles plus
** instances of a few prototypes (batchrt.h, "Instanced scenes").
**
**   landscape  world: the landscape's terrain (grid, skirt and floor, as
**              above).  Prototypes, in this order: 0 spruce, 1 pine (conifers:
**              a trunk, whorls of branches and clusters of lone needle
**              triangles), 2 oak, 3 birch (a trunk, branches and lone leaf
**              triangles about their outer parts), 4 bush, 5 grass tuft,
**              6 boulder, 7 stone.  Trees and bushes grow in forests, each
**              species in its own share of the forests (pure and mixed
**              stands); tufts in meadows; rocks in groups.
**   island     world: the sea (2 triangles), then the islands.  Prototypes:
**              0 palm, 1 leaning palm (a trunk and fronds of lone leaflet
**              triangles), 2 bush, 3 grass tuft, 4 rock, spread over dry land.
**
** Each prototype stands in its own object space: y up, its base point at
** the origin, metres; trunks and stems reach 0.4 m below it into the
** ground, grass 0.1 m, rocks a third of their height.  An instance is rotation about y times a
** uniform scale in [EX_INSTANCE_SCALE_MIN, EX_INSTANCE_SCALE_MAX] (a share
** EX_INSTANCE_TILTED_SHARE of them also tilted by at most
** EX_INSTANCE_MAX_TILT radians), translated to its base point, which lies
** on the world triangles themselves (the plane of the world triangle
** under it, not the smooth height function).  Its condition number is 1
** in the 2-norm up to float rounding, at most 3 in batchrt.h's infinity
** norm: far within BRT_MAX_CONDITION.  A prototype's box is at most about
** 10 m wide and 19 m tall (30 m scaled): no instance spans the scene.
**
** SIZE.  With s the scale and d = max(1, s^(1/4)) the prototypes' detail
** (so instances grow as s, prototype detail more slowly):
**   world triangles     W(s) ~ 92000 s (landscape: its terrain grid gets
**                       55 % of a budget of 100000 s, the
**                       skirt and floor the rest) or ~ 82000 s (island:
**                       the islands' grids share the 55 %);
**   prototype k         P_k(d) ~ a_k + b_k d triangles: leaves, needles
**                       and leaflets (and a rock's grid) grow with d;
**                       trunks, branches and grass tufts stay;
**   instances of k      n_k(s) = round(r_k s), r_k per unit of scale:
**                       landscape 500, 350, 450, 400, 800, 3000, 150, 100
**                       (5750 in all); island 1500, 1000, 2000, 5000, 400
**                       (9900);
**   unique              U = W(s) + sum_k P_k(d)  ~ W(s) at large scales;
**   instanced           I = W(s) + sum_k n_k(s) P_k(d)
**                         ~ W(s) + s (1.8 M + 4.6 M d)   (landscape)
**                         ~ W(s) + s (1.8 M + 2.2 M d)   (island).
** So the paper's sizes: landscape at scale 285 (U about 26 M, I about
** 5.9 G; Table 1: 26 M and 4.3 G), island at scale 1750 (U about 144 M,
** I about 28 G; Table 1: 143 M and 31 G).  Scale 1: about 100 thousand
** unique and a few million instanced triangles.  The landscape's
** instance density stays the same (its side grows as sqrt(s)); the
** island's grows as sqrt(s) (3 sqrt(s) islands).
** ex_instanced_counts gives the exact figures of any scale.
**
** MEMORY.  An open scene holds the placements of its parts (the islands,
** the prototypes' triangle counts and material parts), never triangles
** or instances: instance i is made from (seed, i) alone (counter-based
** random numbers), so the instance stream holds one chunk of
** EX_INSTANCE_CHUNK instances, and ex_instanced_instance is O(1).  The
** streams hold one batch of triangles and three rings of the current
** surface; baked, one prototype and its placed copy besides.
*/

#define EX_INSTANCE_SCALE_MIN 0.6
#define EX_INSTANCE_SCALE_MAX 1.6
#define EX_INSTANCE_TILTED_SHARE 0.1
#define EX_INSTANCE_MAX_TILT 0.15
#define EX_INSTANCE_CHUNK 4096

/* Materials: a diffuse colour each (ex_material_colour). */
typedef enum ex_material {
    EX_MAT_TERRAIN, EX_MAT_ROCK, EX_MAT_SAND, EX_MAT_SEA, EX_MAT_BARK,
    EX_MAT_LEAVES, EX_MAT_NEEDLES, EX_MAT_FRONDS, EX_MAT_GRASS,
    EX_MAT_NONE,        /* no such triangle: magenta, to be seen */
    EX_MAT_COUNT
} ex_material;

typedef struct ex_instanced_scene ex_instanced_scene;

/* Opens "landscape" or "island" at scale s in (0, EX_SCENE_MAX_SCALE]:
** places its parts (no triangles are made).  BRT_EARG for another name or
** scale, BRT_ENOMEM. */
brt_result ex_instanced_open(const char *name, double scale, uint64_t seed,
                             ex_instanced_scene **out, brt_error *err);
void ex_instanced_close(ex_instanced_scene *s);

/* The scene as streams (s must outlive the source): world triangles in
** their order, prototype id's triangles (prim numbers from 0), instances
** in chunks of EX_INSTANCE_CHUNK.  Every run yields the same chunks. */
void ex_instanced_source(const ex_instanced_scene *s, brt_scene_source *source);

/* Unique triangles (world and each prototype once), instanced triangles
** (world plus every instance's prototype) and instances, without making
** any geometry (the cost of ex_instanced_open); they do not depend on the
** seed.  Zeros for an unknown name or a scale out of range. */
void ex_instanced_counts(const char *name, double scale, uint64_t *unique,
                         uint64_t *instanced, uint32_t *instances);

/* The same of an open scene, and its parts. */
uint64_t ex_instanced_unique(const ex_instanced_scene *s);
uint64_t ex_instanced_instanced(const ex_instanced_scene *s);
uint32_t ex_instanced_instance_count(const ex_instanced_scene *s);
uint64_t ex_instanced_world_triangles(const ex_instanced_scene *s);
uint32_t ex_instanced_prototype_count(const ex_instanced_scene *s);
uint64_t ex_instanced_prototype_triangles(const ex_instanced_scene *s, uint32_t id);
const char *ex_instanced_prototype_name(const ex_instanced_scene *s, uint32_t id); /* "oak"; NULL out of range */

/* Instance inst (< ex_instanced_instance_count), as the stream has it. */
void ex_instanced_instance(const ex_instanced_scene *s, uint32_t inst, brt_instance *out);

/* The prototype of instance inst, -1 when there is no such instance
** (instances are numbered in runs of one prototype: all of prototype 0
** first, then all of 1, ...). */
int ex_instanced_instance_prototype(const ex_instanced_scene *s, uint32_t inst);

/* The material of a hit: inst == BRT_NO_INST is world triangle prim (by
** the prim ranges of the world's parts: landscape terrain grid, then its
** skirt and floor (rock); island sea, then sand), else prim of instance
** inst's prototype (trunk and branches first, then leaves, needles or
** fronds).  EX_MAT_NONE when there is no such triangle. */
ex_material ex_instanced_material(const ex_instanced_scene *s, uint32_t inst, uint32_t prim);

/* The diffuse colour (linear RGB in [0, 1]) of a material, and of a hit. */
void ex_material_colour(ex_material m, float rgb[3]);
void ex_instanced_colour(const ex_instanced_scene *s, uint32_t inst, uint32_t prim,
                         float rgb[3]);

#endif
