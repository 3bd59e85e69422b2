/*
** batchrt.h -- the one public header of batchrt, and its manual.
**
** batchrt is a small, dependency-free C99 reference implementation of
** "Conservative Ray Batching using Geometry Proxies" (Molenaar and Eisemann,
** Eurographics 2020), on top of the batched ray traversal of Pharr et al.
** (1997).  Rays wait at large clusters of triangles (batching points) whose
** geometry lives on disk; before a ray is queued it is cast against a small
** in-memory voxel proxy of the cluster, and only rays that hit the proxy
** cause a disk load.  A proxy never misses a ray that hits real geometry.
**
** DATA FLOW (drawn once, in README.md, "The data flow")
**   A mesh (mesh.c) is split into batching points (batchrt.c) and written
**   as a scene file of BVH blobs and proxies (scene.c, bvh.c, svdag.c).
**   Rays walk the top-level BVH; at a point in memory they are intersected
**   at once, elsewhere a proxy test decides whether they queue there; the
**   fullest queue is served from the geometry cache, and its rays walk on
**   to their hits.  The direct mode is one triangle BVH (bvh.c).
**   An instanced scene (brt_scene_source: world triangles, prototypes,
**   instances) takes the same paths: batching points of world triangles
**   and of instances, prototypes' BVHs stored and cached once, the ray
**   carried into each instance it meets (bvh.c, "Instances"); brt_world
**   is its direct mode.  Over several processes (MPI ranks:
**   examples/tools/mpi_trace.c), each owns some batching points, and a ray whose
**   walk stops at a point another owns travels there (brt_exchange).
**
** USAGE: THE BATCHED METHOD (examples/tutorials/minimal_batched.c: a whole program)
**
**   brt_mesh mesh; brt_scene *scene; brt_stats stats; brt_error err;
**   brt_trace_options opt = {0};             // zeroed: the defaults, proxies on
**   if (brt_mesh_load("city.obj", &mesh, &err) != BRT_OK       // 1. the mesh
**       || brt_scene_build(&mesh, NULL, 0, "city.brs", &err)   // 2. batching points,
**          != BRT_OK                                           //    BVH blobs, proxies
**       || brt_scene_open("city.brs", &scene, &err) != BRT_OK) // 3. boxes and proxies
**       { fprintf(stderr, "%s\n", err.message); return 1; }    //    in memory
**   opt.memory_limit = 64 << 20;             // at most 64 MiB of geometry in memory
**   brt_scene_trace(scene, &opt, rays, n, hits, &stats, &err); // 4. hits[i] for rays[i]
**   printf("%llu loads, %llu of %llu proxy tests culled\n",    // 5. what it cost
**          (unsigned long long)stats.batch_loads,
**          (unsigned long long)stats.proxy_culled, (unsigned long long)stats.proxy_tests);
**   brt_scene_close(scene); brt_mesh_free(&mesh);
**
** Every hit is byte for byte the one brt_bvh_intersect finds over the whole
** mesh, whatever the options.  brt_scene_prepare builds a scene file only
** when it is missing or stale; brt_scene_trace_stream keeps a constant
** number of rays in flight (a path tracer).
**
** USAGE: ONE BVH IN MEMORY (examples/tutorials/minimal.c)
**
**   brt_bvh *bvh; brt_hit hit; brt_ray ray = {{0,0,5}, {0,0,-1}, 0, INFINITY};
**   brt_bvh_build(mesh.positions, mesh.indices, mesh.triangle_count, NULL, &bvh);
**   brt_hit_clear(&hit);
**   brt_bvh_intersect(bvh, &ray, &hit);   // hit.prim == BRT_NO_PRIM on a miss
**   brt_bvh_free(bvh);
**
** CONTENTS
**   Results and errors; rays and hits (the records every call takes: base.c)
**   1. Batched traversal: scene files (scene.c), tracing (batchrt.c),
**      statistics (base.c)
**   2. Meshes (mesh.c), triangle streams, instanced scenes and the direct
**      mode's world (world.c)
**   3. Ray and hit files (base.c)
**   4. Ray/triangle test, ray/box test and triangle BVH (bvh.c)
**   5. Conservative voxel proxies: voxelizer, shared DAG, ray cast (svdag.c)
**   6. Small utilities: numbers, files, threads, time (base.c)
**   (Oracles, checkers and hooks for the tests alone: testing.h; what the
**   core files share and no program may use: internal.h; neither installed.)
**
** ERRORS
**   Every fallible function returns a brt_result (BRT_OK is 0) and, when
**   given a non-NULL brt_error, writes a one-line message there that names
**   the file and the place ("mesh.obj:12: face index 9 out of range").
**   The library never prints and never calls exit().
**
** FLOATING-POINT POLICY
**   Build with -std=c99 -ffp-contract=off and never -ffast-math: results
**   are compared byte for byte between traversal orders, and contraction of
**   a*b+c into an FMA would make the same expression round differently in
**   two places.  Bit casts go through memcpy.  Traversal loops have
**   iteration caps and treat NaN as "miss", never as "hang".
**
** RAY AND HIT RECORDS (the file formats; see README.md)
**   ray: float ox,oy,oz, dx,dy,dz, tnear,tfar         (32 bytes)
**   hit: float t; uint32 prim; float u,v               (16 bytes)
**   instanced hit file: a 16-byte header, then per hit
**        float t; uint32 prim; float u,v; uint32 inst  (20 bytes)
**   A hit counts when tnear <= t <= tfar.  The closest hit wins; among
**   equal t the lowest (inst, prim) wins, so every traversal order writes
**   the same bytes.  A miss is t=+inf, prim=inst=0xFFFFFFFF, u=v=0.
**   Barycentrics follow Embree: hit point = (1-u-v)*v0 + u*v1 + v*v2, in
**   the prototype's object space for an instance.
*/
#ifndef BATCHRT_H
#define BATCHRT_H

#include <signal.h>
#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* ===================================================================== */
/* Results and errors (base.c)                                           */
/* ===================================================================== */

typedef enum brt_result {
    BRT_OK = 0,
    BRT_ENOMEM,   /* an allocation failed */
    BRT_EIO,      /* open/read/write/rename failed (errno text in message) */
    BRT_EPARSE,   /* malformed mesh, ray or hit file */
    BRT_EFORMAT,  /* scene file: bad magic, version, checksum or truncation */
    BRT_EARG,     /* an impossible argument or option value */
    BRT_ECHECK,   /* a structural checker found a violated invariant */
    BRT_EINTR     /* stopped: the caller's interrupt flag was set (a signal) */
} brt_result;

/* A one-line human-readable message; message[0] == 0 when there is none. */
typedef struct brt_error {
    char message[512];
} brt_error;

/* Static name of a result code, e.g. "parse error". Never NULL. */
const char *brt_result_string(brt_result r);

/* Sets err->message with printf formatting (err may be NULL) and returns r.
** Used by the library itself; public so examples report errors the same way. */
brt_result brt_fail(brt_error *err, brt_result r, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 3, 4)))
#endif
    ;

/* ===================================================================== */
/* Rays and hits: the records every call takes (base.c)                  */
/* ===================================================================== */

typedef struct brt_ray {
    float org[3];
    float dir[3];   /* need not be normalised; t is in units of dir */
    float tnear;
    float tfar;
} brt_ray;

typedef struct brt_hit {
    float t;        /* +inf on a miss */
    uint32_t prim;  /* BRT_NO_PRIM on a miss; a world triangle's number, or
                    ** the triangle's number within inst's prototype */
    float u, v;     /* 0 on a miss */
    uint32_t inst;  /* the instance hit (Embree's instID); BRT_NO_INST for
                    ** a world triangle and on a miss */
} brt_hit;

#define BRT_NO_PRIM 0xFFFFFFFFu
#define BRT_NO_INST 0xFFFFFFFFu
#define BRT_RAY_BYTES 32
#define BRT_HIT_BYTES 16        /* a hit record without the instance */
#define BRT_INST_HIT_BYTES 20   /* a hit record of an instanced hit file */

/* The one ray-validity rule: nonzero when org and dir are finite, dir is
** not zero and tnear <= tfar (false for a NaN).  The BVH and the batched
** traversal answer "miss" for any other ray; the proxy cast "may hit" (a
** proxy errs only that way). */
int brt_ray_valid(const brt_ray *ray);

/* Sets a hit to the miss record. */
void brt_hit_clear(brt_hit *hit);

/* The one ordering rule of closest hits: nonzero when a hit at (t, inst,
** prim) beats the current one: smaller t; at equal t the lower instance
** (a world triangle's BRT_NO_INST is the highest), then the lower prim. */
int brt_hit_is_closer(float t, uint32_t inst, uint32_t prim, const brt_hit *current);

/* Taken by the batched API, defined further on: a trace's statistics at
** the end of section 1, meshes and triangle sources in section 2. */
typedef struct brt_stats brt_stats;
typedef struct brt_mesh brt_mesh;
typedef struct brt_triangle_source brt_triangle_source;
typedef struct brt_scene_source brt_scene_source;

/* ===================================================================== */
/* 1. Batched traversal: scene files, tracing, statistics               */
/* ===================================================================== */
/*
** A scene file holds a mesh split into batching points.  Each batching
** point has a triangle BVH stored as one blob on disk, a box, and a
** conservative proxy in a DAG pool shared by all of them.  The boxes (in a
** 4-wide top-level BVH), the blob table and the DAG pool are read at open;
** blobs are read on demand through the geometry cache.  See README.md for the
** byte layout.
*/

typedef struct brt_scene brt_scene;

/* How a scene is built; a zeroed struct means the defaults. */
typedef struct brt_scene_options {
    uint32_t point_tris;   /* max triangles per batching point (0: 100000) */
    uint32_t proxy_res;    /* proxy grid resolution, 2^k (0: 128) */
    /* Polled while building: once *interrupt is nonzero (a program's
    ** SIGINT/SIGTERM handler sets it) the build removes its temporary files
    ** and returns BRT_EINTR.  NULL: never interrupted. */
    const volatile sig_atomic_t *interrupt;
    /* Threads building batching points' BVHs and proxies (0: all cores);
    ** the file's bytes do not depend on it. */
    unsigned threads;
    /* Instanced scenes: a batching point of instances is also split while
    ** its instances hold more triangles than this (0: no such limit; the
    ** paper's points hold 10-25 M). */
    uint64_t point_instanced;
    /* Analysis only: each instance's proxy voxels found by testing every
    ** one of its triangles, none pruned; the same voxels (svdag.c,
    ** "Instances"), as slow as the instanced triangles (make bench-paper's
    ** "exactly voxelized"). */
    int exact_voxels;
} brt_scene_options;

/* Builds the scene file for mesh at scene_path (written under a temporary
** name and renamed).  source_stamp identifies the mesh file (see
** brt_scene_source_stamp) so that a stale scene file can be recognised.
** The build holds bounded memory whatever the triangle count (README,
** "Building scene files out of core"): it spills the triangles to a
** temporary file beside scene_path, removed on success, failure and
** interrupt; a failed or interrupted build leaves no file behind. */
brt_result brt_scene_build(const brt_mesh *mesh, const brt_scene_options *opt,
                           uint64_t source_stamp, const char *scene_path,
                           brt_error *err);

/* The same from a triangle stream (see brt_triangle_source): the scene is
** built without the mesh in memory.  brt_scene_build is this over
** brt_mesh_memory_source. */
brt_result brt_scene_build_stream(const brt_triangle_source *source,
                                  const brt_scene_options *opt,
                                  uint64_t source_stamp, const char *scene_path,
                                  brt_error *err);

/* The same for an instanced scene (brt_scene_source): batching points of
** world triangles as above, every prototype's BVH stored once, and
** batching points of instances, each at most point_tris triangles of
** distinct prototypes (counted once however many instances use them;
** more only when a point's instances share one prototype larger than
** that).  A source without prototypes builds brt_scene_build_stream's
** file of its world triangles, byte for byte.  Instances are checked as
** brt_world_build checks them.  The build spills the instances as it
** spills triangles and cuts them a bucket at a time (scene.c, "instance
** points"): it holds one bucket of instances and the prototypes' BVHs,
** never all the instances. */
brt_result brt_scene_build_source(const brt_scene_source *source,
                                  const brt_scene_options *opt, uint64_t source_stamp,
                                  const char *scene_path, brt_error *err);

/* A stamp of a mesh file: its size, modification time (to the nanosecond)
** and inode, hashed into one number -- what make trusts, plus a file
** replaced by another. */
brt_result brt_scene_source_stamp(const char *mesh_path, uint64_t *stamp,
                                  brt_error *err);

/* Opens a scene file: checks magic, version, endianness and every
** checksum of what it reads.  BRT_EFORMAT names the file and the part. */
brt_result brt_scene_open(const char *scene_path, brt_scene **out,
                          brt_error *err);
void brt_scene_close(brt_scene *scene);

/* Nonzero when an open scene was built from this stamp and these options
** (so a caller can reuse it instead of rebuilding); an instanced file whose
** proxies an older build voxelized is stale. */
int brt_scene_matches(const brt_scene *scene, uint64_t source_stamp,
                      const brt_scene_options *opt);

/* Opens scene_path when it matches mesh_path and opt; otherwise (missing
** or stale) builds the scene file from the mesh file streamed (never held
** whole) and opens it.  A corrupt
** or wrong-version file is an error, not silently replaced.  *rebuilt
** tells which happened (may be NULL). */
brt_result brt_scene_prepare(const char *mesh_path, const char *scene_path,
                             const brt_scene_options *opt, brt_scene **out,
                             int *rebuilt, brt_error *err);

/* brt_scene_prepare for a scene source whose input the caller stamps. */
brt_result brt_scene_prepare_source(const brt_scene_source *source, uint64_t source_stamp,
                                    const char *scene_path, const brt_scene_options *opt,
                                    brt_scene **out, int *rebuilt, brt_error *err);

uint32_t brt_scene_point_count(const brt_scene *scene);
/* Prototypes of an instanced scene (0 for a plain one): its hit files
** name instances (brt_hits_write_instanced). */
uint32_t brt_scene_prototype_count(const brt_scene *scene);
/* Triangles stored (world and prototypes, each once) and traced (world
** plus every instance's prototype): equal without instances. */
uint64_t brt_scene_unique_triangles(const brt_scene *scene);
uint64_t brt_scene_instanced_triangles(const brt_scene *scene);
uint32_t brt_scene_instance_count(const brt_scene *scene);
uint32_t brt_scene_triangle_count(const brt_scene *scene);
/* The scene's bounds: the union of the batching points' exact boxes. */
void brt_scene_bounds(const brt_scene *scene, float bmin[3], float bmax[3]);

/* The reader behind the geometry cache: pread's contract (it may return short
** counts or fail with errno EINTR; the cache retries both).  Replaceable
** so that tests can inject faults.  With more than one thread the cache
** also reads ahead: the reader may then be called from a thread of the
** cache's own (never by two threads at once), for a blob that may not be
** used; a failed read-ahead is dropped and the blob read again if needed. */
typedef long (*brt_read_fn)(int fd, void *buf, size_t size, uint64_t offset,
                            void *user);

/* Following one ray through the method (trace --follow): the scheduler
** reports each step of the ray whose tag is follow_tag as it happens.
** point: the batching point; t: where the step happens along the ray;
** hit and visits: the ray's record after the step. */
typedef enum brt_step_kind {
    BRT_STEP_ENTER,         /* the walk enters point's box at t */
    BRT_STEP_INNER,         /* its inner proxy settles the ray occluded */
    BRT_STEP_RESIDENT,      /* its geometry is in memory: intersected at once */
    BRT_STEP_PROXY_HIT,     /* its proxy may hold a hit: first set voxel at t */
    BRT_STEP_PROXY_MISS,    /* its proxy proves a miss: skipped, no load */
    BRT_STEP_QUEUED,        /* queued at point, to wait for its geometry */
    BRT_STEP_LOAD,          /* point's queue is served: bytes read from
                            ** disk for it (0: it was in memory) */
    BRT_STEP_TRIANGLES,     /* point's triangles answered: hit is the
                            ** closest so far (t = +inf: none yet) */
    BRT_STEP_FINISHED       /* the walk is over: hit is the answer */
} brt_step_kind;

typedef struct brt_step {
    brt_step_kind kind;
    uint32_t point;         /* BRT_STEP_FINISHED: 0xFFFFFFFF */
    float t;
    uint64_t bytes;
    brt_hit hit;
    uint32_t visits;        /* batching points visited so far (queued at,
                            ** or intersected at once): brt_ray_source's */
} brt_step;

typedef void (*brt_follow_fn)(void *user, uint64_t tag, const brt_step *step);

/* How a trace runs; a zeroed struct means the defaults. */
typedef struct brt_trace_options {
    uint64_t memory_limit;   /* bytes for geometry (+ proxies); 0: no limit */
    int no_proxy;            /* queue at every box entered, as Pharr et al. */
    int drop_os_cache;       /* cold reads: posix_fadvise(DONTNEED) on the file
                             ** first and on each blob once read, so that a
                             ** blob read again comes from the device, as when
                             ** the file is larger than RAM (otherwise the OS
                             ** keeps the file and hides the memory limit) */
    int paper_scheduler;     /* queue at batching points in memory too and
                             ** always consult the proxies (the paper's
                             ** scheduler); 0: intersect at once in memory,
                             ** and leave the proxies alone when the limit
                             ** holds every batching point */
    int exact_proxies;       /* analysis only: each proxy test becomes an
                             ** exact test against the batching point's
                             ** triangles, all read at the start and not
                             ** counted: what a perfect proxy would cull */
    uint32_t rays_in_flight; /* 0: 4096 when the budget holds every blob
                             ** (and no exchange), else 1 << 20 (layer 2) */
    brt_read_fn read_fn;     /* NULL: pread */
    void *read_user;
    unsigned threads;        /* threads intersecting and walking rays (0:
                             ** all cores); the scheduler's decisions, the
                             ** order of finished calls and every count are
                             ** the same for any number (README, "Threads") */
    int no_inner;            /* do not consult the inner proxies (occlusion
                             ** rays with tfar = +inf; README "Inner proxies") */
    const volatile sig_atomic_t *interrupt;   /* polled before each batch: once
                             ** nonzero (a program's signal handler sets it),
                             ** the trace stops with BRT_EINTR; NULL: never */
    brt_follow_fn follow;    /* NULL, or called at each step of the ray whose
                             ** tag is follow_tag (possibly from a thread of
                             ** the trace's own, never two at once) */
    void *follow_user;
    uint64_t follow_tag;
    const struct brt_exchange *exchange;   /* batching points owned by other
                             ** processes (below, "Beyond one process");
                             ** NULL: this process owns them all */
    int no_decode;           /* keep every batching point quantized, as read
                             ** (0: decode one when the budget has room for
                             ** it beside every blob, layer 8) */
    int reference;           /* the paper's loop, one thread, no layers: for
                             ** reading and for tests (schedule_reference);
                             ** it reads memory_limit, no_proxy,
                             ** rays_in_flight, read_fn, read_user and
                             ** drop_os_cache, and no other option */
    int no_clip;             /* a queued ray's walk in its batching point's
                             ** BVH starts at tnear, not where its proxy
                             ** was entered (layer 10) */
    int no_order;            /* a batch's rays are intersected in queue
                             ** order, not sorted by the voxel where they
                             ** entered the proxy (layer 11) */
    int proxies_in_core;     /* consult the proxies when the budget holds
                             ** every blob too, also at a point in memory
                             ** before its BVH (layers 1 and 4; README,
                             ** "Proxies in core") */
} brt_trace_options;

/* Ray kinds.  A ray of a stream is a closest-hit ray, or an occlusion ray
** when its tag has BRT_TAG_OCCLUSION set: the question "is any triangle hit
** within [tnear, tfar]?" (Embree's rtcOccluded1, brt_bvh_occluded).  An
** occlusion ray finishes at the first hit found anywhere, walks and is
** culled by the proxies like any ray, and comes back to finished with the
** bit still set in its tag and a hit record that says only the answer:
** the miss record when clear; t = 0, prim = 0, u = v = 0 when occluded
** (which triangle is found first depends on the schedule, so none is
** named); the normal is zero.  The flag leaves 63 bits of tag. */
#define BRT_TAG_OCCLUSION ((uint64_t)1 << 63)

/* Stream mode, so a path tracer keeps a constant number of rays in flight:
** the scheduler calls next_rays when it has room for max rays (return how
** many it wrote, at most max -- more is a BRT_EARG error of the trace --
** and 0 when there are no more for now) and finished for every completed ray, in an order that
** depends on the schedule, with the hit triangle's geometric normal (as
** brt_bvh_intersect_normal; zero on a miss) and the number of batching
** points the ray visited: queued at, or intersected at once because their
** geometry was in memory (the paper's Fig. 1 counts these); tag is
** the caller's, passed through.  finished may hand rays to the next next_rays call (a path
** tracer's bounce), so the number in flight stays constant. */
typedef struct brt_ray_source {
    size_t (*next_rays)(void *user, brt_ray *rays, uint64_t *tags, size_t max);
    void (*finished)(void *user, const brt_ray *ray, const brt_hit *hit,
                     const float normal[3], uint32_t visits, uint64_t tag);
    void *user;
} brt_ray_source;

/* Batched traversal: every hit equals brt_bvh_intersect over the whole
** mesh byte for byte, whatever the options.  stats may be NULL. */
brt_result brt_scene_trace_stream(brt_scene *scene,
                                  const brt_trace_options *opt,
                                  const brt_ray_source *source,
                                  brt_stats *stats, brt_error *err);

/* The same for an array of rays (hits[i] for rays[i]). */
brt_result brt_scene_trace(brt_scene *scene, const brt_trace_options *opt,
                           const brt_ray *rays, size_t count, brt_hit *hits,
                           brt_stats *stats, brt_error *err);

/* Occlusion queries for an array of rays: occluded[i] = 1 when some
** triangle is hit within [rays[i].tnear, rays[i].tfar], else 0 -- byte for
** byte brt_bvh_occluded over the whole mesh, whatever the options (the
** occlusion file of README.md). */
brt_result brt_scene_occluded(brt_scene *scene, const brt_trace_options *opt,
                              const brt_ray *rays, size_t count, uint8_t *occluded,
                              brt_stats *stats, brt_error *err);

/* ---- Beyond one process: batching points owned elsewhere ------------- */
/*
** Batched traversal spreads over processes (MPI ranks: examples/tools/mpi_trace.c)
** as it spreads over time: each process owns some batching points, reads
** only their blobs, and holds the top-level BVH and every proxy.  When a
** ray's walk stops at a point another process owns -- after its proxy
** admitted it, so a proxy miss costs no message -- the ray travels there
** with all of its state and is queued there; its walk goes on from there
** and it finishes wherever it ends, its tag unchanged.  Hits stay byte for
** byte those of one process: a hit does not depend on where a ray was
** intersected or in which order (the tie rule is total).
**
** The library knows no transport.  A brt_exchange, named in
** brt_trace_options, gives per batching point whether another process
** owns it, and two calls, both made by the thread that called the trace:
**   send     take one ray for the process that owns ray->key_point (copy
**            it: the record is reused); 0 on success, else the trace fails
**            with BRT_EIO;
**   receive  write up to max rays sent to this process (each queued at its
**            key_point, which this process must own: else BRT_EFORMAT) and
**            return how many.  idle = 0: at once, 0 when none is there.
**            idle = 1: this process has no ray left to work on; block until
**            rays come, and return 0 only when every process is done.
** Whether everyone is done is the transport's to know: mpi_trace counts
** finished rays against the known total (README, "Beyond one machine").
** With an exchange the proxies are always consulted (layer 1 does not turn
** them off): a proxy miss spares a message even when every blob fits.
*/
typedef struct brt_ray_state {
    brt_ray ray;
    brt_hit hit;                /* the closest hit so far (or an occlusion
                                ** ray's record) */
    float normal[3];            /* of that hit's triangle */
    float key_t;                /* the walk's key: entry distance into */
    uint32_t key_point;         /* the batching point it waits at */
    uint32_t visits;            /* batching points visited so far */
    uint32_t pad;               /* 0: the record has no holes */
    uint64_t tag;
} brt_ray_state;

typedef struct brt_exchange {
    const uint8_t *foreign;     /* per batching point: nonzero when another
                                ** process owns it */
    int (*send)(void *user, const brt_ray_state *ray);
    size_t (*receive)(void *user, brt_ray_state *rays, size_t max, int idle);
    void *user;
} brt_exchange;

/* Which of `processes` processes owns each batching point (owner[id], for
** brt_scene_point_count ids): contiguous runs of the top-level BVH's leaf
** order, so that neighbours in space share a process, balanced by the
** bytes each point's loads read (its blob and, for a point of instances,
** its share of the prototypes' bytes); or, with round_robin, the k-th
** point of that order to process k mod processes (the alternative make
** bench-mpi measures).  processes >= 1. */
brt_result brt_scene_assign(const brt_scene *scene, uint32_t processes, int round_robin,
                            uint32_t *owner, brt_error *err);

/* ---- Statistics ------------------------------------------------------ */

/* The fields of the statistics contract (README.md, "Batched mode"); fields that do not apply
** to a mode are 0. */
struct brt_stats {
    uint64_t rays;
    uint64_t batching_points;
    uint64_t geometry_bytes;    /* all batching-point blobs, as stored */
    uint64_t disk_bytes_read;
    uint64_t batch_loads;
    uint64_t cache_peak_bytes;
    uint64_t memory_limit;
    uint64_t proxy_bytes;
    uint64_t proxy_tests;
    uint64_t proxy_culled;
    uint64_t visits;            /* batching points visited by rays: the two below */
    uint64_t queued_visits;     /* rays queued at a batching point */
    uint64_t resident_visits;   /* rays intersected at once: the geometry was in memory */
    uint64_t oversized_loads;   /* loads of a blob larger than the budget */
    uint64_t occlusion_rays;    /* occlusion rays traced (counted in rays too) */
    uint64_t occlusion_hits;    /* of those, the ones that found a hit */
    uint64_t occlusion_batch_loads;     /* loads for a queue of occlusion rays only */
    uint64_t occlusion_disk_bytes_read; /* the bytes those loads read: what the
                                ** occlusion rays alone made the cache read (a
                                ** load for a mixed queue counts for neither) */
    double seconds;             /* tracing */
    double load_seconds;        /* of those, loading batching points (read,
                                ** checksum, open, decode), wall clock */
    double build_seconds;       /* BVH or scene build */
    double bvh_bytes_per_triangle;
    double mrays_per_second;
    uint64_t peak_rss_bytes;    /* the process's, when the stats were taken
                                ** (programs set it: brt_peak_rss_bytes) */
    uint64_t occlusion_inner_stopped;   /* occlusion rays settled occluded by
                                ** an inner proxy: no queue, no load */
    uint64_t prototype_loads;   /* loads of a prototype's blob (instanced
                                ** scenes; counted in disk_bytes_read, not
                                ** in batch_loads) */
    uint64_t decoded_bytes;     /* resident layouts the cache made of BVH
                                ** blobs it holds (layer 8; counted in
                                ** cache_peak_bytes too) */
};

/* Writes the statistics as one JSON object (atomically). */
brt_result brt_stats_write_json(const char *path, const brt_stats *stats,
                                brt_error *err);

/* The same object as text, in a buffer of BRT_STATS_JSON_BYTES, ending
** "\n}\n" (a program adds its own fields before it); returns its length. */
#define BRT_STATS_JSON_BYTES 2048
size_t brt_stats_format_json(const brt_stats *stats, char text[BRT_STATS_JSON_BYTES]);

/* ===================================================================== */
/* 2. Meshes (mesh.c), triangle streams and instanced scenes (world.c)  */
/* ===================================================================== */

/* An indexed triangle mesh.  Triangles are numbered from 0 in file order;
** an OBJ polygon "f a b c d" becomes the fan (a,b,c), (a,c,d).  Degenerate
** triangles keep their number (they never report a hit). */
struct brt_mesh {
    float *positions;         /* 3 floats per vertex */
    uint32_t *indices;        /* 3 vertex indices per triangle */
    uint32_t vertex_count;
    uint32_t triangle_count;
};

/* Loads a Wavefront OBJ ("v", "f" with i, i/t, i//n, i/t/n, negative
** indices) or a PLY (ascii, binary_little_endian, binary_big_endian; float
** or double x y z; face lists of any integer types), chosen by content.
** Streams the file: the text is never held in memory as a whole.
** Errors name the file and line (OBJ, ascii PLY) or element and record
** (binary PLY).  A file without triangles is an error (BRT_EPARSE, "no
** triangles"): every program needs some.  A missing file is BRT_EIO.
** On error *mesh is zeroed; otherwise free it with brt_mesh_free. */
brt_result brt_mesh_load(const char *path, brt_mesh *mesh, brt_error *err);

void brt_mesh_free(brt_mesh *mesh);

/* Axis-aligned bounds of the referenced vertices; an empty mesh gives
** bmin = +inf, bmax = -inf. */
void brt_mesh_bounds(const brt_mesh *mesh, float bmin[3], float bmax[3]);

/* ---- Triangle streams: meshes that are never held whole ---------------- */
/*
** A producer hands triangles to a consumer in chunks, in file order:
** corners holds 9 floats per triangle (v0, v1, v2) and first is the
** file-order number of the chunk's first triangle, so chunk after chunk
** first runs 0, c0, c0 + c1, ...  The consumer returns BRT_OK to go on; any
** other result stops the producer, which returns it (the consumer wrote the
** message into err).  Numbering and error messages are brt_mesh_load's.
*/
typedef brt_result (*brt_triangle_fn)(void *user, const float *corners,
                                      uint32_t count, uint32_t first,
                                      brt_error *err);

/* Something that can produce the same triangles again and again: run
** delivers every triangle once, in order; a build may run it more than once
** (each pass sees the same triangles and the same chunks). */
struct brt_triangle_source {
    brt_result (*run)(const void *user, brt_triangle_fn emit, void *emit_user,
                      brt_error *err);
    const void *user;
};

/* Streams a mesh file (OBJ or PLY, as brt_mesh_load) to emit in chunks of
** 65536 triangles.  Holds the vertex positions of an indexed file (12 bytes
** per vertex) and one chunk, never the triangles (except a PLY whose faces
** come before its vertices: its index array, emitted after the vertices).
** Errors as brt_mesh_load (with "no triangles"), possibly after chunks
** were emitted. */
brt_result brt_mesh_stream(const char *path, brt_triangle_fn emit,
                           void *emit_user, brt_error *err);

/* Sources over a mesh file (path must outlive the source) and over a mesh
** in memory (likewise). */
void brt_mesh_file_source(const char *path, brt_triangle_source *source);
void brt_mesh_memory_source(const brt_mesh *mesh, brt_triangle_source *source);

/* ---- Instanced scenes: world triangles plus instances of prototypes ---- */
/*
** An instance places a prototype (a triangle mesh in its own object space)
** in the world with an affine transform, object to world.  One level
** only: a prototype holds triangles, never instances.  A ray meets an
** instance as in Embree: the ray is carried into object space
** (brt_instance_ray), the watertight test runs there, and t stays the
** world ray's parameter (the transform is affine, so it is the same
** parameter; the hit is the object-space test's t, bit for bit).
*/
typedef struct brt_instance {
    uint32_t prototype;
    /* Object to world, row-major 3x4 (Embree's FLOAT3X4_ROW_MAJOR):
    ** world = M p + d with M's rows xform[0..2], xform[4..6], xform[8..10]
    ** and d = (xform[3], xform[7], xform[11]). */
    float xform[12];
} brt_instance;

/* The largest condition number ||M|| ||M^-1|| (infinity norms) an
** instance's transform may have: the rounding bounds of the ray's transform
** (bvh.c, "Instances") grow with it, and beyond this they stop being
** useful.  Mirrors, shears and scales are all allowed within it. */
#define BRT_MAX_CONDITION 1024.0

/* Instances in chunks, in file order: first is the number of the chunk's
** first instance (instances are numbered 0, 1, ... as triangles are). */
typedef brt_result (*brt_instance_fn)(void *user, const brt_instance *instances,
                                      uint32_t count, uint32_t first,
                                      brt_error *err);

/* A scene as streams, like brt_triangle_source, run as often as a build
** needs: world triangles (world.run may be NULL: none), prototype_count
** prototypes whose triangles prototype() streams (numbered from 0 in its
** order: the prim of a hit on an instance of it), and the instances
** (instances may be NULL: none).  Nested instances cannot be expressed.
** A plain mesh is a source of world triangles alone: world from
** brt_mesh_memory_source, prototype_count 0, instances NULL. */
struct brt_scene_source {
    brt_triangle_source world;
    uint32_t prototype_count;
    brt_result (*prototype)(const void *user, uint32_t id, brt_triangle_fn emit,
                            void *emit_user, brt_error *err);
    brt_result (*instances)(const void *user, brt_instance_fn emit,
                            void *emit_user, brt_error *err);
    const void *user;
};

/* ---- Direct mode over an instanced scene: the whole scene in memory ---- */
/*
** A world is what --direct traces: one triangle BVH over the world
** triangles, one per prototype, and a BVH over the instances' world boxes
** (bvh.c, "Instances").  It is the reference the batched mode of an
** instanced scene matches byte for byte.  Building checks every instance:
** a prototype id out of range, a non-finite or singular transform, or one
** whose condition number exceeds BRT_MAX_CONDITION is BRT_EARG naming the
** instance ("instance 12: ...").
*/
typedef struct brt_world brt_world;
brt_result brt_world_build(const brt_scene_source *source, brt_world **out,
                           brt_error *err);
void brt_world_free(brt_world *world);
/* brt_bvh_intersect_normal's contract over the world (normal may be NULL;
** an instance's normal is its world triangle's (v1-v0) x (v2-v0)). */
void brt_world_intersect(const brt_world *world, const brt_ray *ray,
                         brt_hit *hit, float normal[3]);
int brt_world_occluded(const brt_world *world, const brt_ray *ray);
/* brt_bvh_trace's contract over the world. */
void brt_world_trace(const brt_world *world, const brt_ray *rays,
                     const uint64_t *tags, size_t count, brt_hit *hits,
                     float *normals, unsigned threads);
uint32_t brt_world_instance_count(const brt_world *world);
uint32_t brt_world_prototype_count(const brt_world *world);
/* Unique triangles (world and prototypes, each once) and instanced ones
** (world triangles plus every instance's prototype triangles). */
uint64_t brt_world_unique_triangles(const brt_world *world);
uint64_t brt_world_instanced_triangles(const brt_world *world);
/* The world's bounds: its triangles' exact bounds and its instances'
** boxes (brt_instance_bounds) -- the same floats as brt_scene_bounds of
** the scene file built from the same source. */
void brt_world_bounds(const brt_world *world, float bmin[3], float bmax[3]);

/* ===================================================================== */
/* 3. Ray and hit files (base.c)                                         */
/* ===================================================================== */

/* Little-endian files of records.  Ray files and the hit files of scenes
** without instances have no header; an instanced hit file starts with the
** 16-byte header le32 0x7FB1A5E5 (a NaN, which no hit's t ever is, so the
** two forms cannot be confused), "INST", le32 1 (version), le32 20 (record
** bytes), then 20-byte records.  Reading a file whose size does not fit
** its form is BRT_EPARSE; brt_hits_read reads either form (*instanced,
** when not NULL, says which; a short record's inst is BRT_NO_INST).
** brt_hits_write writes the short form and refuses (BRT_EARG) a hit that
** names an instance; brt_hits_write_instanced writes the long form.
** Writing goes through brt_write_file_atomic.  *rays / *hits are
** malloc'd (free()). */
brt_result brt_rays_read(const char *path, brt_ray **rays, size_t *count,
                         brt_error *err);
brt_result brt_rays_write(const char *path, const brt_ray *rays, size_t count,
                          brt_error *err);
brt_result brt_hits_read(const char *path, brt_hit **hits, size_t *count,
                         int *instanced, brt_error *err);
brt_result brt_hits_write(const char *path, const brt_hit *hits, size_t count,
                          brt_error *err);
brt_result brt_hits_write_instanced(const char *path, const brt_hit *hits,
                                    size_t count, brt_error *err);

/* ===================================================================== */
/* 4. Ray/triangle test, ray/box test and triangle BVH (bvh.c)           */
/* ===================================================================== */

/* Watertight ray/triangle test of Woop, Benthin and Wald (2013).  On a hit
** with tnear <= t <= tfar returns 1 and sets *t, *u, *v (Embree's
** barycentrics).  Rays with a NaN, an all-zero direction or tnear > tfar
** never hit.  The BVH uses bit-for-bit the same arithmetic, so a brute-force
** loop over this function is an exact oracle for the BVH. */
int brt_intersect_triangle(const brt_ray *ray, const float v0[3],
                           const float v1[3], const float v2[3],
                           float *t, float *u, float *v);

/* The one ray/box test of batchrt, used by the triangle BVH, the
** triangle clamp of brt_intersect_triangle and the top-level walk.  The
** box is grown by 16 * FLT_EPSILON of its largest |coordinate| and the
** origin moved by the same share of its own (towards the box for near
** planes, away for far planes); then per axis t = (plane - origin) * inv,
** entry = max(tmin, near planes), exit = min(tmax, far planes).  (A zero
** direction component gives inf * 0 = NaN on a slab plane, which never
** narrows the interval: a ray in the plane of a closed slab is inside.)
** Every step rounds monotonically in the box bounds, so a box inside
** another is entered no earlier and left no later, bit for bit: with the
** triangle clamp this makes pruning by "entry > closest t" exact. */
typedef struct brt_ray_prep {
    float inv[3];        /* 1/dir (+-inf for a zero component) */
    float org_near[3];   /* origin for near planes, moved towards them */
    float org_far[3];    /* origin for far planes, moved away from them */
    int negative[3];     /* dir[a] has its sign bit set: near plane is hi */
    float tnear, tfar;
    int valid;     /* 0: NaN or inf in org/dir, zero dir, NaN t, tnear > tfar */
} brt_ray_prep;

void brt_ray_prepare(const brt_ray *ray, brt_ray_prep *prep);

typedef struct brt_bvh brt_bvh;   /* opaque; layout documented in bvh.c */

/* Builds a BVH over tri_count triangles given by indices into positions.
** prim_ids[i] is the number reported for triangle i (NULL: i itself).
** tri_count may be 0 (every ray misses).  A NaN or inf coordinate of a
** triangle is BRT_EARG. */
brt_result brt_bvh_build(const float *positions, const uint32_t *indices,
                         uint32_t tri_count, const uint32_t *prim_ids,
                         brt_bvh **out);
void brt_bvh_free(brt_bvh *bvh);

/* Closest hit.  hit is in/out: it is replaced only by a closer hit (in the
** sense of brt_hit_is_closer) within [ray->tnear, min(ray->tfar, hit->t)],
** so one hit record can be carried across several BVHs (batching points)
** and the final bytes do not depend on their order. */
void brt_bvh_intersect(const brt_bvh *bvh, const brt_ray *ray, brt_hit *hit);

/* The same, and whenever the hit changes, normal becomes the geometric
** normal (v1-v0) x (v2-v0) of the new hit's triangle (not normalised;
** its direction follows the triangle's winding).  Shading needs it, and in
** batched mode the triangle is only in memory while its batching point is. */
void brt_bvh_intersect_normal(const brt_bvh *bvh, const brt_ray *ray,
                              brt_hit *hit, float normal[3]);

/* brt_bvh_intersect_normal for count rays from cleared hits: hits[i] (and
** normals[3i..3i+2] when normals is not NULL, zero on a miss) for rays[i],
** in chunks spread over threads threads (0: all cores).  tags may be NULL;
** otherwise a ray whose tags[i] has BRT_TAG_OCCLUSION is an occlusion ray
** and gets brt_ray_source's record (t = 0, prim = 0 when occluded, else the
** miss record).  Out of memory for the threads, it runs on fewer; the bytes
** are the same either way. */
void brt_bvh_trace(const brt_bvh *bvh, const brt_ray *rays, const uint64_t *tags,
                   size_t count, brt_hit *hits, float *normals, unsigned threads);

/* Any hit in [tnear, tfar]: 1 if occluded. */
int brt_bvh_occluded(const brt_bvh *bvh, const brt_ray *ray);

/* The bytes the BVH holds: nodes, vertices, prim ids and corner indices
** (the blob less its 64-byte header), plus, for a BVH built in memory,
** its resident layout (bvh.c). */
size_t brt_bvh_memory_bytes(const brt_bvh *bvh);

/* ---- Instances: one function carries a ray into a prototype ---------- */

/* What intersection needs of an instance, derived once from its transform
** by brt_instance_frame_init (which checks it: finite, non-singular,
** condition number at most BRT_MAX_CONDITION; else BRT_EARG naming
** instance number inst). */
typedef struct brt_instance_frame {
    double inverse[9];    /* M^-1, row-major */
    double translation[3];/* d: object = M^-1 (world - d) */
    float cofactor[9];    /* det(M) M^-T, row-major: world normals */
    float condition;      /* ||M|| ||M^-1||, infinity norms */
    float norm;           /* ||M|| */
} brt_instance_frame;

brt_result brt_instance_frame_init(const brt_instance *instance, uint32_t inst,
                                   brt_instance_frame *frame, brt_error *err);

/* The world ray in object space: origin and direction through the inverse
** in double, each rounded once to float; tnear and tfar unchanged. */
void brt_instance_ray(const brt_instance_frame *frame, const brt_ray *ray,
                      brt_ray *object_ray);

/* An instance's world box: the 8 corners of the prototype's box
** (brt_bvh_bounds) through the transform in double, rounded outwards;
** and its radius, which the margin below needs: the largest distance
** from d to the box plus a term for underflow (infinity norms, rounded
** up). */
void brt_instance_bounds(const brt_instance *instance, const brt_instance_frame *frame,
                         const float obj_lo[3], const float obj_hi[3],
                         float lo[3], float hi[3], float *radius);

/* The margin by which a box of instances grows for one ray so that pruning
** stays exact under the rounding of the ray's transform (bvh.c,
** "Instances", proves the bound): condition is the largest of the box's
** instances, and reach, about center, the largest |d - center| + radius.
** 0 when condition is 0 (no instances), so a plain scene's traversal is
** unchanged. */
float brt_instance_margin(float condition, float reach, const float center[3],
                          const brt_ray *ray);

/* ===================================================================== */
/* 5. Voxel proxies: voxelizer, shared DAG, ray cast (svdag.c)           */
/* ===================================================================== */

/* Nonzero when res is a resolution a grid or proxy may have: 2^k,
** k = 1..10 (the one rule; brt_proxy_check and the scene build use it). */
int brt_proxy_res_valid(uint32_t res);

/* A dense binary voxel grid with cubic cells, fitted to a box.
** Voxel (x,y,z) covers origin + cell*[x,x+1] x [y,y+1] x [z,z+1]; its bit is
** bits[i >> 6] >> (i & 63) with i = x + res*(y + res*z). */
typedef struct brt_grid {
    uint32_t res;       /* 2^k, k = 1..10 */
    float origin[3];
    float cell;         /* edge length of a voxel */
    uint64_t *bits;
} brt_grid;

/* Allocates an empty grid of res^3 voxels whose cubic cells cover the box
** [bmin, bmax] (the grid is as long as the longest side). */
brt_result brt_grid_init(brt_grid *grid, const float bmin[3],
                         const float bmax[3], uint32_t res);
void brt_grid_free(brt_grid *grid);
int brt_grid_get(const brt_grid *grid, uint32_t x, uint32_t y, uint32_t z);
void brt_grid_set(brt_grid *grid, uint32_t x, uint32_t y, uint32_t z);
uint64_t brt_grid_count(const brt_grid *grid);   /* voxels set */

/* Conservative voxelization: marks every voxel whose closed box a triangle
** touches (under rounding: never misses one; may add a few neighbours).
** Degenerate triangles mark the voxels they touch.  Visits only voxels in
** each triangle's bounding box. */
brt_result brt_voxelize(brt_grid *grid, const float *positions,
                        const uint32_t *indices, uint32_t tri_count);

typedef struct brt_svdag brt_svdag;  /* a node pool shared by many proxies */

/* One proxy: a root in the shared pool plus the grid frame it came from. */
typedef struct brt_proxy {
    uint32_t root;      /* node index, or BRT_EMPTY_ROOT for an empty grid */
    uint32_t res;
    float origin[3];
    float cell;
} brt_proxy;
#define BRT_EMPTY_ROOT 0xFFFFFFFFu

brt_result brt_svdag_create(brt_svdag **out);
void brt_svdag_free(brt_svdag *dag);

/* Adds a grid as a proxy: SVO built bottom-up, every node deduplicated
** against the whole pool (hash plus full comparison), so identical
** sub-blocks -- also across proxies -- are stored once. */
brt_result brt_svdag_add(brt_svdag *dag, const brt_grid *grid,
                         brt_proxy *proxy);

/* Laine-Karras ray cast adapted to the DAG, on the world-space segment
** [tnear, tfar] along ray (ray->tnear/tfar are ignored).  Returns 1 when the
** segment touches the closed box of a set voxel, with *t_entry no greater
** than where it first touches one (clamped to tnear).  Conservative under
** rounding; NaN rays return 1 with *t_entry = tnear (a proxy may only err
** towards "hit").  t_entry may be NULL: the cast then stops at the first
** set voxel it touches (the yes/no question the batched traversal asks).
** The proxy must have passed brt_proxy_check against this pool (done once,
** when a proxy is built or read: the cast does not check it again; an
** unchecked proxy may read outside the pool). */
int brt_proxy_raycast(const brt_svdag *dag, const brt_proxy *proxy,
                      const brt_ray *ray, float tnear, float tfar,
                      float *t_entry);

/* Nodes of the proxy's tree before deduplication (the SVO: interior nodes
** plus 4x4x4 leaves), counted through the DAG; 0 for an empty or invalid
** proxy or when memory runs out. */
uint64_t brt_svdag_svo_nodes(const brt_svdag *dag, const brt_proxy *proxy);

/* Inner voxelization (svdag.c, "Inner proxies").  A solids set: the
** closed components of a set of triangles (every edge used an even number
** of times by triangles with exactly equal vertex positions, none
** degenerate); triangle t's corners are the 9 floats at corners + stride * t,
** which the set refers to: keep them until brt_solids_free. */
typedef struct brt_solids brt_solids;
brt_result brt_solids_build(const float *corners, size_t stride, uint32_t tri_count,
                            brt_solids **out);
uint32_t brt_solids_triangles(const brt_solids *solids);   /* in closed components */
void brt_solids_free(brt_solids *solids);

uint32_t brt_svdag_node_count(const brt_svdag *dag);
size_t brt_svdag_memory_bytes(const brt_svdag *dag);

/* ===================================================================== */
/* 6. Small utilities: numbers, files, threads, time (base.c)            */
/* ===================================================================== */

/* Parses a size such as "512", "64K", "512M", "2G" (powers of 1024).
** Rejects empty, negative, zero, overflowing and trailing-garbage text. */
brt_result brt_parse_size(const char *text, uint64_t *bytes);

/* The one 64-bit mixer (SplitMix64's finaliser): a bijection whose
** outputs for neighbouring inputs look independent; hashes and
** counter-based random numbers are built on it. */
uint64_t brt_mix64(uint64_t x);

/* SplitMix64: a tiny deterministic generator for raygen and the tests.
** brt_random_float returns a float uniformly in [0, 1). */
uint64_t brt_random_u64(uint64_t *state);
float brt_random_float(uint64_t *state);

/* The 64-bit checksum of scene files (header, sections, blobs): a
** word-wise multiply-xorshift hash, not cryptographic. */
uint64_t brt_checksum64(const void *data, size_t size);

/* Little-endian numbers, the byte order of every file batchrt writes. */
void brt_put_le32(unsigned char *p, uint32_t v);
void brt_put_le64(unsigned char *p, uint64_t v);
uint32_t brt_get_le32(const unsigned char *p);
uint64_t brt_get_le64(const unsigned char *p);

/* The growable array: returns items with room for need elements of size
** bytes (*cap elements: at least doubled, or to need, and updated), or
** NULL when out of memory, items then untouched (still the caller's to
** free).  With need <= *cap it returns items as they are. */
void *brt_grow(void *items, size_t *cap, size_t need, size_t size);

/* Seconds from a monotonic clock, for statistics only. */
double brt_seconds(void);

/* The process's peak resident set so far, in bytes (getrusage's ru_maxrss);
** 0 where the system does not say. */
uint64_t brt_peak_rss_bytes(void);

/* Threads (README, "Threads"): every option named threads means that many
** POSIX threads, the caller's included; 0 means one per online core, and
** at most BRT_MAX_THREADS.  No output byte and no count depends on it. */
#define BRT_MAX_THREADS 256u

/* Writes size bytes to path through "path.tmp.<pid>" and rename(), so a
** failure never leaves a half-written file under the final name.  A path
** that names a device or a pipe (/dev/null, /dev/stdout) is written in
** place instead: renaming over it would replace it. */
brt_result brt_write_file_atomic(const char *path, const void *data,
                                 size_t size, brt_error *err);

/* The same for a file written piece by piece: brt_atomic_open creates
** "path.tmp.<pid>" (fd open for writing; fdopen it for stdio, and set fd to
** -1 after fclose); brt_atomic_close(f, r, err) closes fd, then renames
** the file over path when r is BRT_OK, else removes it, and returns r or
** the close or rename failure.  Call it after every brt_atomic_open,
** failed or not. */
typedef struct brt_atomic_file {
    const char *path;           /* the final name */
    char tmp[4096];             /* the temporary name; "" when none was created */
    int fd;                     /* -1 once closed */
} brt_atomic_file;
brt_result brt_atomic_open(brt_atomic_file *f, const char *path, brt_error *err);
brt_result brt_atomic_close(brt_atomic_file *f, brt_result r, brt_error *err);

#ifdef __cplusplus
}
#endif
#endif /* BATCHRT_H */
