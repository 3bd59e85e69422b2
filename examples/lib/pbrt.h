/*
** examples/lib/pbrt.h -- a streaming reader of pbrt-v4 scene files (the
** triangle geometry, its transforms, object instancing and the camera),
** feeding batchrt's scene stream (brt_scene_source, batchrt.h section 2).
** It follows the pbrt-v4 file format (pbrt.org/fileformat-v4) and, where
** the text is silent, pbrt-v4's parser.cpp and scene.cpp.
**
** USAGE
**
**   ex_pbrt *pbrt; brt_scene_source source; brt_error err;
**   float eye[3], target[3], up[3], fov;
**   if (ex_pbrt_open("view-0.pbrt", &pbrt, &err) != BRT_OK)   // reads the
**       { fprintf(stderr, "%s\n", err.message); return 1; }  // structure once
**   ex_pbrt_source(pbrt, &source);        // world triangles, prototypes,
**                                         // instances: streams, run as often
**                                         // as a build needs
**   if (ex_pbrt_camera(pbrt, eye, target, up, &fov, NULL)) ...
**   if (*ex_pbrt_skipped(pbrt)) fprintf(stderr, "%s\n", ex_pbrt_skipped(pbrt));
**   ...
**   ex_pbrt_close(pbrt);                  // after the last run of source
**
** STREAMING.  ex_pbrt_open tokenizes the whole file tree once and keeps,
** per triangle shape, where its numbers are (file and byte offset) and the
** transform in force; per object its shapes; per instance its object and
** transform (a brt_instance each, 52 bytes).  The streams read the numbers
** again from disk when run.  Memory grows with the number of shapes and
** instances, never with triangles: ex_pbrt_open holds a window of 1 MiB
** per open file, and a run one window, one shape's vertex positions (12
** bytes a vertex) and one chunk of 65536 triangles (tests/test_pbrt.c
** checks the peak resident set against a 40 MB mesh).  A loopsubdiv is
** the exception: it is held whole while refined, its control mesh and
** two levels at once (examples/lib/loopsubdiv.h), once at ex_pbrt_open (its
** indices, to check them) and once per run.
**
** WHAT IS READ
**   Shape "trianglemesh"  "point3 P" and "integer indices" (indices may be
**                         left out when P has exactly 3 points).
**   Shape "bilinearmesh"  "point3 P", "integer indices", 4 per patch (may
**                         be left out for exactly 4 points).  pbrt's patch
**                         corners are p00, p10, p01, p11; patch (a,b,c,d)
**                         becomes the triangles (a,b,d) and (a,d,c), in
**                         that order: (p00,p10,p11), (p00,p11,p01).
**   Shape "plymesh"       "string filename", read by brt_mesh_stream; a
**                         name ending in ".gz" is unpacked first by the
**                         system's "gzip -dc" into a temporary file under
**                         $TMPDIR (default /tmp), removed however the
**                         read ends; without gzip it is an error.
**   Shape "loopsubdiv"    "point3 P", "integer indices", "integer levels"
**                         (default 3; 0 or less: none), refined as pbrt-v4
**                         refines it when it loads a scene, in object space,
**                         the limit points then transformed
**                         (examples/lib/loopsubdiv.h: Loop's rules, boundary
**                         rules, the push to the limit surface, and the
**                         order: control face i becomes the shape's
**                         triangles i 4^levels .. (i+1) 4^levels - 1).
**                         "string scheme" is read and ignored, as pbrt-v4
**                         ignores it; pbrt-v3's "nlevels" is skipped.
**   Identity Translate Scale Rotate LookAt Transform ConcatTransform
**   CoordinateSystem CoordSysTransform ("camera" too) ActiveTransform
**   AttributeBegin/End TransformBegin/End ObjectBegin/End ObjectInstance
**   Include Import WorldBegin Camera "perspective"
**   ("fov", "screenwindow", "frameaspectratio"), Film ("xresolution",
**   "yresolution"), a shape's constant "float alpha".
**   Every other directive and shape is read (its parameters consumed) and
**   skipped, and counted in ex_pbrt_skipped's summary; so is every
**   parameter a read directive does not use ("Shape parameter \"uv\"",
**   N, S, "Camera parameter \"lensradius\"", a Film's filename, ...), and
**   WorldEnd (pbrt-v3's).
**
** SEMANTICS (pbrt-v4's)
**   - The current transform (CTM) is post-multiplied: Translate makes
**     CTM = CTM * T, so the last transform written acts first on a point.
**     Transform and ConcatTransform list a matrix column by column (pbrt
**     transposes what it reads): the translation is numbers 13, 14, 15.
**     Rotate is in degrees about an axis, right-handed as pbrt's Rotate.
**     Only affine matrices are read (last row 0 0 0 1).
**   - Only the start-time transform is kept: under "ActiveTransform
**     EndTime" transforms change nothing (motion blur is ignored).
**   - WorldBegin resets the CTM to the identity.  A file without
**     WorldBegin (a geometry file opened on its own) is all world.
**   - World shapes are baked to world space with the CTM at the shape;
**     their triangles are numbered from 0 in file order across shapes.
**   - Object instancing, one level.  A prototype is one ObjectBegin's
**     shapes, each baked with the full CTM in force at the shape (pbrt's
**     renderFromObject of the shape, world-relative: the CTM before
**     ObjectBegin included), triangles numbered in file order within the
**     object.  Prototypes are numbered in ObjectBegin order.  An instance
**     is (prototype, the CTM at ObjectInstance): pbrt-v4 puts an
**     instance's shapes at renderFromInstance * renderFromShape, which in
**     world space is CTM(ObjectInstance) * CTM(shape).  ObjectInstance may
**     name an object defined further on (pbrt-v4 resolves names at the
**     end), never one that is not defined at all.
**   - Include is textual: the graphics state goes into the included file
**     and comes back changed.  Import starts with the importer's state,
**     and at its end the state is restored (pbrt-v4 parses it with a copy
**     of the builder): its transforms stay in it; a block it opens must
**     close in it, and it cannot close the importer's.  What it defines
**     (shapes, objects, instances) is kept, in file order.  Named
**     coordinate systems are one table for all files.
**   - Relative paths (Include, Import, plymesh) resolve against the folder
**     of the main scene file, as pbrt does, not the including file's.
**   - Camera "perspective": the CTM at Camera is camera-from-world, kept
**     whole (pbrt's camera looks down +z, +y up, the image's right is
**     camera +x): handedness, LookAt's up vector and any transform after
**     LookAt are the file's.  A bare LookAt is left-handed: with "LookAt
**     0 0 10  0 0 0  0 1 0" world +x is on the image's LEFT; files from
**     right-handed tools start "Scale -1 1 1".  ex_pbrt_camera_frame is
**     pbrt-v4's PerspectiveCamera: the screen window spans [-1,1] on the
**     shorter side of the frame (frameaspectratio, default the image's
**     width / height) and [-frame, frame] on the longer, unless
**     "screenwindow" gives x0 x1 y0 y1; "fov" (default 90) spans [-1,1];
**     raster y points down.  ex_pbrt_camera is the same camera as eye,
**     target, up and fov (*mirrored: pbrt's image is the mirror of the
**     right-handed view eye/target/up describe, as for a bare LookAt).
**   - Film: "xresolution" and "yresolution" (default 1280 and 720) are
**     the image size render and raygen use (ex_pbrt_film).
**   - "alpha": pbrt-v4 never reports a hit where alpha is 0, so a shape
**     whose constant "float alpha" is 0 is left out of the scene (counted
**     as "Shape removed by \"alpha\" 0").  Alpha 1 is opaque.  Between, pbrt
**     lets hits through at random, and a "texture alpha" depends on the
**     hit: both keep the shape opaque here and are reported as skipped.
**   - Blocks: AttributeBegin, TransformBegin and ObjectBegin each close
**     with their own End, innermost first (pbrt-v4 reads TransformBegin/End
**     as AttributeBegin/End; a file that mixes them is refused here).
**   - Materials, lights, normals, uv and ReverseOrientation are ignored:
**     they do not change which triangle a ray hits first.
**
** ERRORS.  BRT_EPARSE (or BRT_EIO for files that cannot be read, BRT_ENOMEM)
** with one line naming the file and line, e.g.
** "scene.pbrt:12: ObjectInstance of unknown object \"tree\"": unknown
** directive or parameter type, an End that does not close the innermost
** open block with its own kind (or a block never closed), a screenwindow
** of other than 4 numbers, a fov outside (0, 180), nested ObjectBegin, ObjectInstance inside
** ObjectBegin, an Include cycle, a missing file, P not a multiple of 3,
** indices not a multiple of 3 (4 for bilinearmesh) or out of range, a
** loopsubdiv without indices, a non-manifold one (an edge in more than two
** faces, two faces running an edge the same way, a vertex in no face or
** where separate fans of faces meet, a face repeating a vertex: where
** pbrt-v4 crashes, loops or drops faces; examples/lib/loopsubdiv.h) or one
** refined past 2^20 triangles, a
** non-finite number, a non-affine matrix, a singular transform at a shape,
** an instance or the camera, an instance's transform or the camera's
** position beyond the float range.  (The condition-number limit of
** instances, BRT_MAX_CONDITION, is the library's to check.)  The streams
** report errors the same way (a PLY file's are brt_mesh_stream's): a
** point that overflows the float range through its shape's transform
** (BRT_EPARSE), BRT_EIO when a file changed after ex_pbrt_open read it.
** Control characters of names in messages and in the summary (a "\n"
** escape in a string) are shown as '?': every message is one line.
*/
#ifndef BRT_EXAMPLES_PBRT_H
#define BRT_EXAMPLES_PBRT_H

#include "batchrt.h"

typedef struct ex_pbrt ex_pbrt;   /* a parsed scene description: opaque */

/* Reads the structure of the scene file at path and every file it
** includes (see above).  On error *out is NULL. */
brt_result ex_pbrt_open(const char *path, ex_pbrt **out, brt_error *err);

/* Frees the description; the sources made from it must not be run again. */
void ex_pbrt_close(ex_pbrt *scene);

/* The scene as streams: world triangles (world.run is NULL when there is
** no world triangle shape), one prototype per ObjectBegin, the instances
** in file order (prototype numbers are ObjectBegin order).  A run reads
** the files again; runs may happen at once from several threads. */
void ex_pbrt_source(const ex_pbrt *scene, brt_scene_source *source);

/* Counts of what ex_pbrt_open found: triangle shapes in the world (not
** counting shapes inside ObjectBegin), prototypes and instances. */
void ex_pbrt_counts(const ex_pbrt *scene, uint64_t *world_shapes,
                    uint32_t *prototypes, uint32_t *instances);

/* The scene's unique triangles, from the structure alone (for the default
** point size): every shape once, world and prototypes, however many
** instances use it; a trianglemesh's indices / 3, a bilinearmesh's two a
** patch, a loopsubdiv's after refinement, a plymesh's its header's face
** count (ex_mesh_file_triangles: a lower bound for polygons; 0 for a
** gzipped one, whose header is not unpacked for this). */
uint64_t ex_pbrt_triangles(const ex_pbrt *scene);

/* The perspective camera, when the file has one (returns 1; 0 and the
** outputs untouched when not): eye, target, up, pbrt's fov in degrees
** across the shorter image axis, and *mirrored (may be NULL) as explained
** above. */
int ex_pbrt_camera(const ex_pbrt *scene, float eye[3], float target[3],
                   float up[3], float *fov_degrees, int *mirrored);

/* The Film's resolution, pbrt-v4's 1280x720 for what the file leaves out
** (returns 1 when the file has a Film directive, 0 when not). */
int ex_pbrt_film(const ex_pbrt *scene, uint32_t *width, uint32_t *height);

/* pbrt-v4's perspective camera over a width x height image, as pbrt
** defines it (above): the ray through image point (sx, sy) in [0,1]^2,
** raster order (sx right, sy down, (0,0) the top left corner of the
** image), leaves eye along forward + (2 sx - 1) right + (1 - 2 sy) up
** (examples/lib/rays.h's ex_camera).  Returns 0 (outputs untouched) when the
** file has no perspective camera. */
int ex_pbrt_camera_frame(const ex_pbrt *scene, uint32_t width, uint32_t height, double eye[3],
                         double forward[3], double right[3], double up[3]);

/* What was read and skipped, in order of first appearance, e.g.
** "skipped: 120 MakeNamedMaterial, 6 AreaLightSource, 1 Shape \"sphere\"";
** "" when nothing was skipped.  Lives as long as the scene. */
const char *ex_pbrt_skipped(const ex_pbrt *scene);

#endif
