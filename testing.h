/*
** testing.h -- what batchrt offers its tests and fuzz targets alone, as
** Lua's ltests.h and SQLite's SQLITE_TEST interfaces do: not installed
** (make install copies batchrt.h only), so no program can come to rely
** on it.
**
** ORACLES AND CHECKERS (first part) change nothing; every build of the
** library holds them, and its own sources include this header to have
** their prototypes.
**
** HOOKS (second part) change what the library does, to force rare paths
** on small inputs: they exist only in a library compiled with
** BRT_TESTING, which the Makefile builds for the test runner alone
** ($(BUILD)/tests/libbatchrt_testing.a).  Each is a variable of the
** process, not of a scene or a call: the runner puts every hook back to
** its default before each test (tests/main.c, run_one); set them from
** one thread, between calls.  The release library ($(BUILD)/libbatchrt.a,
** the one installed) has none, and so keeps no global state (runner: the
** hooks are in the runner's copy of the library alone).
*/
#ifndef BRT_TESTING_H
#define BRT_TESTING_H

#include "internal.h"

#ifdef __cplusplus
extern "C" {
#endif

/* ===================================================================== */
/* Oracles and checkers (in every build)                                 */
/* ===================================================================== */

/* brt_mesh_load's parsers on a memory buffer; name is used in messages. */
brt_result brt_mesh_parse_obj(const char *name, const void *data, size_t size,
                              brt_mesh *mesh, brt_error *err);
brt_result brt_mesh_parse_ply(const char *name, const void *data, size_t size,
                              brt_mesh *mesh, brt_error *err);

/* The one-box form of brt_box_span4 (batchrt.h, section 4), the tests'
** oracle for it: 1 when the ray's segment [tmin, tmax] meets the closed
** box [lo, hi], which must already be grown with brt_box_pad (so that a
** caller testing one box many times grows it once), with the entry and
** exit distances. */
int brt_box_span(const brt_ray_prep *prep, const float lo[3],
                 const float hi[3], float tmin, float tmax, float *entry,
                 float *exit);

/* Bounds of the root's decoded boxes: the triangles' bounds grown by a
** few ulps of their magnitude (bvh.c: the pad that makes box tests
** conservative for the rounding of the triangle test), then rounded
** outward to the root's 8-bit planes; +inf/-inf when empty. */
void brt_bvh_bounds(const brt_bvh *bvh, float bmin[3], float bmax[3]);

/* Structural checker: every triangle in exactly one leaf, indices in
** range, slots ordered, and every triangle's grown box inside the decoded
** (quantized) box of every slot on its path from the root -- what makes
** pruning exact; a BVH built in memory also has its resident layout
** compared, byte for byte, with the quantized nodes decoded (bvh.c).
** BRT_ECHECK with a message naming the first violation. */
brt_result brt_bvh_check(const brt_bvh *bvh, brt_error *err);

/* The resident layout of a BVH built in memory (bvh.c) with one bit
** flipped: bit at / size % 8 of byte at % size, where size (returned) is
** the layout's bytes; 0 (nothing flipped) for a BVH without one.  For
** the tests of brt_bvh_check. */
size_t brt_bvh_damage_resident(brt_bvh *bvh, uint64_t at);

/* Pool checker: child indices in range and pointing to earlier nodes,
** masks consistent, no two identical nodes. */
brt_result brt_svdag_check(const brt_svdag *dag, brt_error *err);

/* Decodes a proxy back into a dense grid (allocated here). */
brt_result brt_svdag_decode(const brt_svdag *dag, const brt_proxy *proxy,
                            brt_grid *grid);

/* brt_proxy_raycast written for reading: plain Laine-Karras (INITIALIZE,
** PUSH, ADVANCE, POP, the paper's names), slower; same contract.
** It answers hit or miss exactly as brt_proxy_raycast does, with the same
** *t_entry (the same plane distances; tests check both). */
int brt_proxy_raycast_reference(const brt_svdag *dag, const brt_proxy *proxy,
                                const brt_ray *ray, float tnear, float tfar,
                                float *t_entry);

/* Partition checker: every triangle number below the scene's triangle
** count is in exactly one batching point, and no batching point holds more
** than point_tris triangles (it reads every blob).  BRT_ECHECK with a
** message naming the first violation. */
brt_result brt_scene_check_partition(const brt_scene *scene, uint32_t point_tris,
                                     brt_error *err);

#ifdef BRT_TESTING
/* ===================================================================== */
/* Hooks (only with BRT_TESTING)                                         */
/* ===================================================================== */

/* Injects one read fault: the library's own reads (brt_pread_reader: a scene
** file's header, tables and blobs, the spill file of a build) succeed
** `after` more times, then one fails with errno `error`; after < 0 never
** (the default). */
void brt_test_read_fault(long after, int error);

/* brt_intersect_triangle with (on, the default) or without the early
** rejection of triangles behind the segment (bvh.c, "behind the
** segment"): the tests compare both on every ray.  The BVH walks always
** reject early. */
void brt_test_early_reject(int on);

/* The sizes of every later scene build (0: the defaults).  spill_chunk:
** triangles per write buffer of a bucket and per read of the build's
** temporary file (default 16384); bucket_tris: the most triangles of one
** bucket held in memory, rounded down to a multiple of point_tris and at
** least point_tris (default 64 MiB of 40-byte records).  Small values
** run the out-of-core paths of the build on small meshes.  Neither
** changes what a scene file built from a mesh that fits one bucket
** holds.  (The instance pass of an instanced scene takes buckets of a
** quarter of bucket_tris instances, whatever point_tris.) */
void brt_test_build_sizes(uint32_t spill_chunk, uint32_t bucket_tris);

/* Counts, while on, the instanced triangles brt_voxelize_instance hands to
** the triangle test (svdag.c, "Instances"): the work of the pruned
** voxelization against every triangle.  Turning it on zeroes the count;
** on from one thread only (the count is a plain integer). */
void brt_test_count_instance_triangles(int on);
uint64_t brt_test_instance_triangles(void);

/* Turns on (off by default) the counting behind brt_test_node_visits and
** brt_test_bottom_level: plain integers, so from one thread, with no other
** trace running meanwhile (the tests run traces on several threads at
** once).  brt_test_count_nodes: bvh.c's alone. */
void brt_test_count_bottom(int on);
void brt_test_count_nodes(int on);

/* The BVH nodes every walk has visited while counting (bvh.c). */
uint64_t brt_test_node_visits(void);

/* Called, while set, for each ray a batch intersects (batchrt.c, layers
** 10 and 11), in the order intersected, from the plain loop (one thread):
** the batching point, the ray's place in that order (0 starts a batch),
** its tag, the ray as its BVH walk starts (tnear clipped by layer 10) and
** its entry voxel's Morton code. */
typedef void (*brt_test_batch_fn)(void *user, uint32_t point, uint32_t place, uint64_t tag,
                                  const brt_ray *ray, uint32_t entry_voxel);
void brt_test_on_batch_ray(brt_test_batch_fn fn, void *user);

/* The batches' intersections while counting, in the plain loop (one
** thread): rays, the BVH nodes their walks visited and their wall seconds
** (make bench-order's bottom level). */
void brt_test_bottom_level(uint64_t *rays, uint64_t *nodes, double *seconds);

#endif /* BRT_TESTING */

#ifdef __cplusplus
}
#endif
#endif /* BRT_TESTING_H */
