/*
** internal.h -- what the core files of batchrt share and no program may
** use.  Not installed (make install copies batchrt.h only), so a
** declaration here may change with any release; batchrt.h is the manual
** of the public API alone.
**
** The core files, from the top down; a file calls only its own row and
** the rows below it:
**
**     batchrt.c  the method: partition, top-level walk, scheduler, cache
**     scene.c    the scene file: format, out-of-core build, open, checks
**     world.c    the direct mode's world: an instanced scene in memory
**     mesh.c     OBJ and PLY input
**     svdag.c    the voxel proxies (an instance's through its BVH)
**     bvh.c      the triangle test and the BVH
**     base.c     rays and hits, errors, statistics, utilities, threads
**
** The first three are one row: the build cuts points with the method's
** partition, the scheduler reads blobs through the scene file's reads,
** and the world and the build gather triangle streams alike.  None of
** the rows below calls up, and base.c needs nothing ("runner: the core
** files stand in layers" holds it, with nm).
*/
#ifndef BRT_INTERNAL_H
#define BRT_INTERNAL_H

#include "batchrt.h"
#include <pthread.h>

/* ===================================================================== */
/* The scene in memory: the types batchrt.c, scene.c and world.c share   */
/* ===================================================================== */
/* Their design is told where they are used: batchrt.c, "the partition
** into batching points", "the top-level BVH", "instances" and "the scene
** in memory". */

typedef struct batch_range {
    uint32_t first, count;        /* into the triangle order */
} batch_range;

typedef struct partition {
    uint32_t *order;              /* triangle ids, batching point by batching point
                                  ** (the caller's array) */
    batch_range *ranges;
    uint32_t count;
    size_t capacity;
} partition;

typedef uint64_t (*range_size_fn)(void *user, const uint32_t *ids, uint32_t n,
                                  uint32_t *distinct, uint64_t *instanced);

typedef struct size_limits {
    uint32_t point_tris;          /* distinct prototype triangles */
    uint64_t point_instanced;     /* instanced triangles; 0: none */
} size_limits;

#define TOP_EMPTY 0xFFFFFFFFu   /* an unused child slot: never entered */
#define TOP_LEAF 0x80000000u    /* child code of batching point (code & ~TOP_LEAF) */
#define TOP_NODE_BYTES 112

typedef struct top_node {
    float box[6][4];            /* child boxes: rows min x, y, z, max x, y, z; one lane
                                ** per child (grown in memory; brt_box_span4's layout) */
    uint32_t child[4];          /* node index (> own index), TOP_LEAF|id, TOP_EMPTY */
} top_node;

/* The margin of a box of instances (bvh.c, "Instances"), taken about the
** box's centre, so that it is as small as the box's neighbourhood allows
** wherever the box lies: the largest condition number of its instances,
** and the largest |d - center| + radius (brt_instance_bounds). */
typedef struct instance_margin {
    float condition, reach;
    float center[3];
} instance_margin;

typedef struct instance_set {
    uint32_t count;
    uint32_t *ids;                  /* the instances' numbers (hit.inst) */
    uint32_t *prototypes;           /* their prototypes */
    brt_instance_frame *frames;
    top_node *nodes;                /* boxes grown by brt_top_node_pad */
    uint32_t node_count;
    instance_margin margin;         /* about the centre of all their boxes */
    uint32_t *uses;                 /* batched mode: the distinct prototypes, */
    uint32_t use_count;             /* ascending (what a load must make resident) */
    void *mapping;                  /* a loaded table's arrays: one anonymous */
    size_t mapping_bytes;           /* mapping (brt_instance_table_open); NULL:
                                    ** each array malloc'd (the direct mode) */
} instance_set;

/* What a ray is intersected with: a batching point's geometry, or the
** whole scene's (direct mode).  Either part may be absent (NULL). */
typedef struct geometry {
    const brt_bvh *triangles;
    const instance_set *instances;
    const brt_bvh *const *prototypes;   /* by prototype id */
} geometry;

/* A point of instances' proxy marks what lies within this share of a
** voxel of its instances' triangles: the rounding of the ray's transform
** it covers (proxy_admits, brt_voxelize_instance).  A small share keeps
** the proxy tight; rays from farther away than it covers are admitted
** untested. */
#define INSTANCE_DILATION (1.0f / 64.0f)

/* A median-split tree of four groups per node is at most about
** log4(count) + 1 deep (17 for 2^32 instances); each level leaves at most
** three siblings on the stack. */
#define SET_STACK 64

typedef struct point_entry {
    float lo[3], hi[3];
    uint64_t offset, size, checksum;
    uint32_t triangles;         /* world triangles; for a point of instances,
                                ** its distinct prototypes' triangles */
    brt_proxy proxy;
    brt_proxy inner;            /* inner proxy; the file holds its root, its
                                ** frame follows from the box (inner_frame) */
    uint32_t instances;         /* 0: a point of world triangles (its blob a
                                ** BVH); else a point of instances (its blob
                                ** an instance table, "instance points") */
    uint64_t instanced;         /* the triangles of its instances */
    instance_margin margin;     /* its instances', about its box's centre */
} point_entry;

/* A prototype of an instanced scene: its BVH blob, stored once and cached
** once whichever batching points use it, and its object-space box. */
typedef struct proto_entry {
    uint64_t offset, size, checksum;
    uint32_t triangles;
    float lo[3], hi[3];         /* brt_bvh_bounds of its BVH */
} proto_entry;

typedef struct section {
    uint64_t offset, size, checksum;
} section;

/* What the header says, unpacked. */
typedef struct scene_header {
    uint64_t stamp, geometry_bytes;
    uint32_t point_tris, proxy_res, point_count, triangle_count, top_node_count;
    section sections[4];        /* the fourth: prototypes (instanced files) */
    /* Instanced scenes (version 4) only: */
    uint32_t prototype_count, instance_count;
    uint64_t instanced_triangles;
    instance_margin margin;     /* of all instances: the walk's */
    uint64_t point_instanced;   /* brt_scene_options.point_instanced */
    uint32_t instance_voxels;   /* INSTANCE_VOXELS_* of its proxies; 0: older */
} scene_header;

/* A blob opened: a BVH (a point of world triangles, or a prototype) or
** an instance table (a point of instances), referring into the blob. */
typedef struct blob_view {
    brt_bvh *bvh;
    instance_set *set;
} blob_view;

/* Where a blob lies: the blobs are the batching points' (ids 0 ..
** point_count - 1) and then the prototypes'. */
typedef struct blob_place {
    uint64_t offset, size, checksum;
} blob_place;

struct brt_scene {
    char *path;
    int fd;
    scene_header header;
    point_entry *points;
    proto_entry *prototypes;    /* instanced scenes, else NULL */
    blob_place *blobs;          /* point_count + prototype_count */
    top_node *top;
    brt_svdag *dag;
    uint64_t file_size;
};

#define SCENE_PAGE 4096u   /* blobs start at multiples of it (the scene file) */

struct prepared_ray;   /* batchrt.c: a ray prepared for the box test once */

/* ---- batchrt.c: the partition, the top-level tree, instances and their intersection (the build, the world and the scheduler) ---- */
brt_result brt_partition_split(partition *p, const float *centroids, uint32_t first, uint32_t count,
                               uint32_t point_tris);
brt_result brt_partition_by_size(partition *p, const float *centres, uint32_t first, uint32_t count,
                                 const size_limits *limits, range_size_fn size_of, void *user);
brt_result brt_top_build(const float *boxes, uint32_t count, top_node **nodes,
                         uint32_t *node_count);
void brt_top_lane_clear(top_node *node, int lane);
void brt_top_lane_grow(top_node *node, int lane, const float *box);
void brt_margin_begin(instance_margin *m, const float lo[3], const float hi[3]);
void brt_margin_add(instance_margin *m, const brt_instance_frame *f, float radius);
brt_result brt_instance_admit(const brt_instance *in, uint32_t number, uint32_t prototypes,
                              brt_instance_frame *frame, brt_error *err);
brt_result brt_set_build_tree(instance_set *set, const float *boxes);
void brt_set_fit_margin(instance_set *set, const float *boxes, const float *radii);
void brt_set_free(instance_set *set);
void brt_intersect_ray(const geometry *g, const brt_ray *ray, uint64_t tag, brt_hit *hit,
                       float normal[3], const struct prepared_ray *p);
void brt_trace_geometry(const geometry *g, const brt_ray *rays, const uint64_t *tags, size_t count,
                        brt_hit *hits, float *normals, unsigned threads);

/* ---- scene.c: the scene file's reads and the top-level nodes it stores ---- */
brt_result brt_read_fully(int fd, void *buf, size_t size, uint64_t offset, brt_read_fn read_fn,
                          void *user, uint64_t *bytes_read, const char *path, brt_error *err);
long brt_pread_reader(int fd, void *buf, size_t size, uint64_t offset, void *user);
uint64_t brt_round_up_page(uint64_t n);
void brt_top_node_pad(top_node *n);
brt_result brt_instance_table_open(const brt_scene *s, uint32_t id, const unsigned char *data,
                                   uint64_t size, instance_set **out, brt_error *err);
void brt_bounds_grow(float lo[3], float hi[3], const float p[3]);

/* ---- world.c: a triangle stream gathered into a BVH (the world and the prototypes of a build) ---- */
brt_result brt_stream_bvh(brt_result (*run)(const void *, uint32_t, brt_triangle_fn, void *,
                          brt_error *), const void *user, uint32_t id, brt_bvh **out,
                          uint32_t *count, float *lo, float *hi, brt_error *err);
brt_result brt_run_prototype_stream(const void *user, uint32_t id, brt_triangle_fn emit,
                                    void *emit_user, brt_error *err);

/* ---- the BVH and instances, for the scene file, the cache and the proxies (bvh.c) ---- */

/* Grows the box [lo, hi] as above (by 16 * FLT_EPSILON of its largest
** |coordinate|, every bound rounded outwards by the same float ops);
** plo/phi may be lo/hi themselves. */
void brt_box_pad(const float lo[3], const float hi[3], float plo[3], float phi[3]);

/* A prepared ray's box-test constants in four lanes each, and the rows
** of a [6][4] box that hold each axis's near and far planes (as indices
** and byte offsets): what brt_box_span4 loads as vectors.  A walk that
** tests many nodes sets them once (brt_box_lanes_of), not at each node. */
typedef struct brt_box_lanes {
    float org_near[3][4], org_far[3][4], inv[3][4];
    int near_row[3], far_row[3];
    size_t near_off[3], far_off[3];
} brt_box_lanes;

void brt_box_lanes_of(const brt_ray_prep *prep, brt_box_lanes *lanes);

/* brt_box_span (section 7) on four padded boxes at once, laid out as rows of four
** lanes: box[0..2] the minimum x, y, z and box[3..5] the maximum x, y, z
** of lanes 0..3 (a 4-wide BVH node).  Bit i of the result is lane i's
** answer; entry[i] and exit[i] are bit for bit brt_box_span's. */
unsigned brt_box_span4(const brt_box_lanes *lanes, const float box[6][4],
                       float tmin, float tmax, float entry[4], float exit[4]);

/* brt_bvh_intersect_normal, or with any != 0 brt_bvh_occluded (1 when
** occluded; hit and normal unused), of a ray already prepared:
** brt_ray_prepare of this very ray (no margin) and brt_box_lanes_of it.
** For walks that meet many BVHs with one ray: the top-level walk hands
** its preparation to each batching point it intersects at once. */
int brt_bvh_walk_prepared(const brt_bvh *bvh, const brt_ray *ray, const brt_ray_prep *prep,
                          const brt_box_lanes *lanes, brt_hit *hit, float normal[3], int any);

uint32_t brt_bvh_triangle_count(const brt_bvh *bvh);
/* The number reported for each stored triangle, in storage order
** (brt_bvh_triangle_count of them; checkers read it). */
const uint32_t *brt_bvh_prim_ids(const brt_bvh *bvh);

/* A BVH as one relocatable blob (indices, no pointers, little-endian) for
** the scene file.  brt_bvh_blob_open makes a BVH that refers to the blob's
** memory (which must stay alive and be 16-byte aligned) after validating
** its sizes, indices and slot order, its decoded boxes (ordered) and
** vertices (finite), and that every triangle number it reports is below
** prim_limit (a scene's triangle count; UINT32_MAX when there is none); a
** corrupt blob is BRT_EFORMAT, never a crash or a wrong hit record later
** (a big-endian host refuses blobs: they are read in place). */
size_t brt_bvh_blob_size(const brt_bvh *bvh);
void brt_bvh_blob_write(const brt_bvh *bvh, void *dst);
brt_result brt_bvh_blob_open(const void *blob, size_t size, uint32_t prim_limit,
                             brt_bvh **out, brt_error *err);

/* The resident layout (bvh.c) for a BVH opened from a blob: its quantized
** boxes decoded once to floats and its leaves copied into blocks of four,
** so no walk decodes a node again (make bench-embree times both); the
** same hits, bit for bit.
** brt_bvh_decoded_bytes says what brt_bvh_decode would allocate (0 when
** the BVH has it already or is empty); brt_bvh_decode adds it (BRT_OK, or
** BRT_ENOMEM and the BVH unchanged).  The geometry cache decodes a
** batching point when the budget has room for it (batchrt.c, layer 8). */
size_t brt_bvh_decoded_bytes(const brt_bvh *bvh);
brt_result brt_bvh_decode(brt_bvh *bvh);

/* Visits a BVH's boxes depth first, for voxelizing an instance without
** visiting every triangle: box(user, lo, hi) gets every slot's decoded box
** (which holds its triangles' grown boxes, brt_bvh_check); when it returns
** nonzero, an inner slot's children are visited, and triangle() gets each
** triangle of a leaf slot. */
typedef int (*brt_bvh_box_fn)(void *user, const float lo[3], const float hi[3]);
typedef void (*brt_bvh_corner_fn)(void *user, const float *v0, const float *v1,
                                  const float *v2);
void brt_bvh_visit(const brt_bvh *bvh, brt_bvh_box_fn box, brt_bvh_corner_fn triangle,
                   void *user);

/* The one instance intersection of every mode: brt_bvh_intersect_normal
** of the prototype's BVH with the object ray, the hit naming inst (normal
** may be NULL; it becomes the world normal). */
void brt_instance_intersect(const brt_bvh *prototype,
                            const brt_instance_frame *frame, uint32_t inst,
                            const brt_ray *ray, brt_hit *hit, float normal[3]);
int brt_instance_occluded(const brt_bvh *prototype,
                          const brt_instance_frame *frame, const brt_ray *ray);

/* brt_ray_prepare with every box it tests grown by margin >= 0 on all
** sides (the origin moved by margin more, which is the same). */
void brt_ray_prepare_margin(const brt_ray *ray, float margin, brt_ray_prep *prep);

/* ---- proxies, for the scene build and the scheduler (svdag.c) ---- */

/* How brt_voxelize_instance visits a prototype's BVH; both mark the same
** voxels.  INSTANCE_VOXELS_PRUNED skips every node whose voxels are set
** already (the scene build); INSTANCE_VOXELS_EVERY_TRIANGLE tests each
** triangle (the analysis of brt_scene_options.exact_voxels, and the
** tests' model).  Nonzero: a scene header stores it, 0 for older files. */
enum { INSTANCE_VOXELS_PRUNED = 1, INSTANCE_VOXELS_EVERY_TRIANGLE = 2 };

/* Conservative voxelization of an instance (prototype under an object-to-
** world xform, brt_instance's layout): marks every voxel whose closed box,
** grown by dilation (world units, >= 0) and by the voxelizer's bound on
** rounding, touches a transformed triangle: the SAT of brt_voxelize on
** each, the transform evaluated in double (svdag.c, "Instances").  mode:
** INSTANCE_VOXELS_*. */
brt_result brt_voxelize_instance(brt_grid *grid, const brt_bvh *prototype,
                                 const float xform[12], float dilation, int mode);

/* Checks a proxy against a pool (e.g. one read from a scene file): res a
** power of two in 2..1024, finite origin, finite positive cell, and root
** an empty root or a node of the pool of the depth res needs.
** BRT_ECHECK with a message. */
brt_result brt_proxy_check(const brt_svdag *dag, const brt_proxy *proxy,
                           brt_error *err);

/* Into an allocated, empty grid: the voxels whose closed box lies inside a
** closed component of solids (odd crossing parity), so that a ray from any
** of them to infinity hits a triangle of solids. */
brt_result brt_voxelize_inner(brt_grid *inner, const brt_solids *solids);

/* 1 only when the ray, with tfar = +inf, certainly hits a triangle at
** t >= tnear: it passes through the core of an inner voxel of the proxy
** (a root from brt_voxelize_inner's grid, checked like an outer proxy).
** 0 for any other ray, or when unsure: it may under-report, never
** over-report. */
int brt_inner_occludes(const brt_svdag *dag, const brt_proxy *inner,
                       const brt_ray *ray);

/* The pool as one relocatable blob, for the scene file (little-endian,
** layout in svdag.c).  brt_svdag_blob_open copies the blob (any alignment)
** and runs brt_svdag_check: a corrupt blob is BRT_EFORMAT.  Proxies read
** from the same file are then validated with brt_proxy_check. */
size_t brt_svdag_blob_size(const brt_svdag *dag);
void brt_svdag_blob_write(const brt_svdag *dag, void *dst);
brt_result brt_svdag_blob_open(const void *blob, size_t size,
                               brt_svdag **out, brt_error *err);

/* ---- threads (base.c) ---- */

/* The number of threads an option's request stands for (batchrt.h,
** BRT_MAX_THREADS): at least 1, at most BRT_MAX_THREADS. */
unsigned brt_threads_resolve(unsigned threads);

/* ---- the pool of threads (base.c) ---- */
/* The scene build, the scheduler's phases and the direct mode's chunks run
** their jobs on it: brt_pool_run hands [0, total) out in chunks to
** job(ctx, thread, first, end), then commit(ctx, first, end), when not
** NULL, sees the chunks in order. */
typedef void (*brt_pool_job)(void *ctx, unsigned thread, size_t first, size_t end);
typedef void (*brt_pool_commit)(void *ctx, size_t first, size_t end);

typedef struct brt_pool {
    pthread_mutex_t lock;
    pthread_cond_t wake, idle, progress;
    pthread_t *threads;
    unsigned count;             /* threads that run jobs, the caller included */
    unsigned long round;        /* incremented for each job */
    unsigned busy;              /* threads still in the current job */
    int quit;
    brt_pool_job job;
    void *ctx;
    size_t next, total, chunk;  /* the split of the current job */
    unsigned char *done;        /* per chunk of the job: finished */
    size_t done_cap;
} brt_pool;

void brt_pool_init(brt_pool *p, unsigned threads);
void brt_pool_run(brt_pool *p, brt_pool_job job, brt_pool_commit commit, void *ctx, size_t total,
                  size_t chunk);
void brt_pool_free(brt_pool *p);

/* The largest vertex or triangle count: one below UINT32_MAX, which
** marks "none" in the files. */
#define MAX_COUNT 0xFFFFFFFEu

/* ---- files (base.c) ---- */
/* Writes all of data at offset, or at the file position when offset is
** negative: 0, or -1 with errno set. */
int brt_write_fully(int fd, const void *data, size_t size, int64_t offset);
/* Nonzero when path exists and is not a regular file (a device, a pipe):
** a rename over it would replace it. */
int brt_is_special_file(const char *path);

#endif
