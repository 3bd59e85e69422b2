/*
** examples/lib/input.h -- the geometry a program reads: a mesh file (Wavefront
** OBJ or PLY, batchrt.h section 2) or a pbrt-v4 scene file (".pbrt",
** examples/lib/pbrt.h), which may hold instances.  Every program that takes a
** mesh takes either, through these calls; they exit with a one-line
** message naming the file on bad input.
*/
#ifndef BRT_EXAMPLES_INPUT_H
#define BRT_EXAMPLES_INPUT_H

#include "batchrt.h"
#include "pbrt.h"
#include "count.h"

typedef struct ex_input {
    const char *path;
    ex_pbrt *pbrt;              /* a .pbrt file, else NULL (a mesh file) */
    brt_scene_source source;    /* the geometry as streams */
    uint64_t stamp;             /* a .pbrt file's brt_scene_source_stamp */
    int instanced;              /* it has prototypes: hit files name instances */
} ex_input;

/* Nonzero when path names a pbrt scene file (by its ".pbrt" ending). */
int ex_input_is_pbrt(const char *path);

/* Opens the input (a .pbrt file's structure is read; a mesh file is read
** when needed, so its errors are the mesh reader's).  Prints what a pbrt
** file had that batchrt skips, on stderr. */
void ex_input_open(const char *prog, const char *path, ex_input *in);
void ex_input_close(ex_input *in);

/* The input's unique triangles: a mesh file's (ex_mesh_file_triangles), a
** pbrt file's world triangles plus every prototype's once (ex_pbrt_triangles). */
uint64_t ex_input_triangles(const ex_input *in);

/* Direct mode: the whole scene in memory (brt_world_build). */
brt_world *ex_input_world(const char *prog, const ex_input *in);

/* Batched mode: the scene file at scene_path, reused when it matches the
** input's stamp and opt, else built from the streams
** (brt_scene_prepare_source).  A pbrt file's stamp is its main file's:
** after editing only an included file, pass --rebuild. */
brt_scene *ex_input_scene(const char *prog, const ex_input *in, const char *scene_path,
                          const brt_scene_options *opt, int *rebuilt);

/* The geometry bytes of an open scene (all blobs, as the statistics give
** them), from a trace of no rays: a limit given as a share needs it before
** the real trace. */
uint64_t ex_scene_geometry_bytes(const char *prog, brt_scene *scene);

/* The whole input as one mesh in memory, for the analysis programs
** (voxelize, closed): a mesh file as brt_mesh_load reads it; a pbrt file
** flattened: its world triangles, then each instance's prototype
** triangles through its transform (in double, rounded once), instance
** after instance.  Dies on bad input. */
void ex_input_load_mesh(const char *prog, const char *path, brt_mesh *mesh);

/* Writes hits in the form the input calls for: the instanced hit file
** when it has prototypes, else the plain one (batchrt.h section 3). */
brt_result ex_input_write_hits(const ex_input *in, const char *path, const brt_hit *hits,
                               size_t count, brt_error *err);

#endif
