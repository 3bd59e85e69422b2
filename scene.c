/*
** scene.c -- the scene file: what holds the batching points between the
** build and the trace.  Its layout (little-endian, page-aligned blobs),
** the out-of-core build that writes it (spill file, buckets, batching
** points, the instance pass), opening it, and validating every byte a
** trace will rely on before the first ray.  The method (batchrt.c) reads
** blobs from it through the geometry cache; the layout is in README.md
** ("The scene file") too.
*/
#define _DEFAULT_SOURCE
#include "internal.h"
#include "testing.h"

#if !defined(BRT_DEBUG) && !defined(NDEBUG)
#define NDEBUG
#endif
#include <assert.h>
#include <errno.h>
#include <fcntl.h>
#include <float.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include <pthread.h>
#include <sys/mman.h>
#include <sys/stat.h>

/* TUNABLES of the out-of-core build ("Building a scene file out of core"
** below): memory against passes over the spill file; no byte of the scene
** file depends on them (make bench-scale measures the build). */
#define CELL_BITS 7                      /* Morton cells per axis of a split: 2^21
                                         ** cells, fine enough for one split level */
#define BUCKET_BYTES ((size_t)64 << 20)  /* records of one bucket: the build's
                                         ** largest buffer, under its 256 MiB */
#define SCATTER_BYTES ((size_t)16 << 20) /* all write buffers of a split: large
                                         ** writes, whatever the cells */
#define SPILL_CHUNK 16384u               /* records per read and buffer: large
                                         ** reads, small against a bucket */

/* ===================================================================== */
/* Scene files                                                           */
/* ===================================================================== */

/* ---- checksums and little-endian floats ------------------------------- */

/* Word-wise multiply-xorshift hash (in the style of MurmurHash's
** finaliser): fast enough to verify every blob on every load, and a random
** corruption goes unnoticed with probability about 2^-64.  Not a
** cryptographic hash.  Not built on brt_mix64 (the one mixer): its steps
** are part of the scene-file format -- every file written holds its sums,
** and changing them would change those bytes. */
uint64_t brt_checksum64(const void *data, size_t size)
{
    const unsigned char *p = data;
    uint64_t h = 0x9E3779B97F4A7C15ull ^ (uint64_t)size, w;
    for (; size >= 8; p += 8, size -= 8) {
        memcpy(&w, p, 8);
        h = (h ^ w) * 0xFF51AFD7ED558CCDull;
        h ^= h >> 32;
    }
    w = 0;
    memcpy(&w, p, size);
    h = (h ^ w) * 0xC4CEB9FE1A85EC53ull;
    return h ^ (h >> 29);
}

/* Every number of a scene file is little-endian (brt_put_le32 and its
** kin), like ray and hit files (version 2; version 1 used the writer's
** byte order).  The BVH blobs inside it are little-endian too and read in
** place (bvh.c). */
static void put_f32(unsigned char *p, float v) { uint32_t w; memcpy(&w, &v, 4); brt_put_le32(p, w); }
static float get_f32(const unsigned char *p) { uint32_t w = brt_get_le32(p); float v; memcpy(&v, &w, 4); return v; }

/* ---- the scene file --------------------------------------------------- */
/*
** Layout, version 3 (all numbers little-endian; the mark is kept so
** that a file of version 1 written on a big-endian host is named as such):
**   header, 256 bytes:
**     0 "BRTSCENE"  8 u32 version  12 u32 endianness mark 0x01020304
**     16 u64 source stamp  24 u32 point_tris  28 u32 proxy_res
**     32 u32 batching points  36 u32 triangles  40 u32 top-level nodes
**     44 u32 0  48 u64 geometry bytes (all blobs)
**     56 three sections {u64 offset, u64 size, u64 checksum}:
**        point table, top-level nodes, DAG pool
**     248 u64 checksum of bytes 0..247
**   blobs: one triangle BVH per batching point (brt_bvh_blob_write), each
**     at a multiple of SCENE_PAGE, so the cache reads whole aligned pages
**   point table: POINT_ENTRY_BYTES per batching point: f32 lo[3] hi[3],
**     u64 blob offset, u64 blob size, u64 blob checksum, u32 triangles,
**     u32 proxy root, u32 proxy res, f32 proxy origin[3], f32 cell,
**     u32 inner proxy root (version 3; its frame follows from the box)
**   top-level nodes: TOP_NODE_BYTES each (f32 lo[3][4] hi[3][4], u32 child[4])
**   DAG pool: brt_svdag_blob_write
** The file is padded to a multiple of SCENE_PAGE.
**
** Version 4, a scene with instances, adds to version 3:
**   header: 44 u32 prototypes; 128 a fourth section {offset, size,
**     checksum}: the prototype table; 152 u32 instances; 156 f32 largest
**     condition number; 160 f32 reach (instance_margin); 164 u32 0;
**     168 u64 instanced triangles; 176 f32 the margin's centre[3];
**     192 u64 point_instanced (brt_scene_options); 200 u32 how the proxies
**     were voxelized (INSTANCE_VOXELS_*; 0 in a file of an older build,
**     which brt_scene_matches finds stale)
**   point table entries of POINT_ENTRY_BYTES_V4: the 80 bytes above, then
**     u32 instances (0: a point of world triangles), f32 condition, u64
**     instanced triangles, f32 reach, u32 0 (the margin of its instances,
**     about its box's centre)
**   prototype table: PROTO_ENTRY_BYTES per prototype: u64 blob offset,
**     u64 blob size, u64 blob checksum, u32 triangles, f32 lo[3] hi[3],
**     u32 0
**   blobs: a prototype's BVH (brt_bvh_blob_write, triangles numbered in
**     its stream's order); a point of instances' instance table
**     ("instance points" below)
** A file without instances is written as version 3, byte for byte.
*/
#define SCENE_MAGIC "BRTSCENE"
#define SCENE_VERSION 3u   /* 3: inner proxy roots (README "Inner proxies") */
#define SCENE_VERSION_INSTANCED 4u
#define POINT_ENTRY_BYTES_V4 104
#define PROTO_ENTRY_BYTES 56
#define SECTION_PROTOTYPES 3
#define SCENE_ENDIAN_MARK 0x01020304u
#define SCENE_HEADER_BYTES 256
#define POINT_ENTRY_BYTES 80
#define SECTION_POINTS 0
#define SECTION_TOP 1
#define SECTION_DAG 2

/* Inner proxies are stored at half the proxy resolution (at least 2): at
** full resolution their surface nodes, unique like the outer proxy's,
** grow the pool that the geometry budget pays for; at a quarter they stop
** too few rays.  make bench-inner prints both the pool's bytes and the
** rays they settle. */
static uint32_t inner_res(uint32_t proxy_res)
{
    return proxy_res >= 4 ? proxy_res / 2 : 2;
}

uint64_t brt_round_up_page(uint64_t n)
{
    return (n + SCENE_PAGE - 1) / SCENE_PAGE * SCENE_PAGE;
}

static void batch_entry_pack(const point_entry *b, unsigned char *p)
{
    int a;
    memset(p, 0, POINT_ENTRY_BYTES);
    for (a = 0; a < 3; a++) {
        put_f32(p + 4 * a, b->lo[a]);
        put_f32(p + 12 + 4 * a, b->hi[a]);
        put_f32(p + 60 + 4 * a, b->proxy.origin[a]);
    }
    brt_put_le64(p + 24, b->offset);
    brt_put_le64(p + 32, b->size);
    brt_put_le64(p + 40, b->checksum);
    brt_put_le32(p + 48, b->triangles);
    brt_put_le32(p + 52, b->proxy.root);
    brt_put_le32(p + 56, b->proxy.res);
    put_f32(p + 72, b->proxy.cell);
    brt_put_le32(p + 76, b->inner.root);
}

/* The instanced table's entry: version 3's, then the instance fields. */
static void batch_entry_pack_v4(const point_entry *b, unsigned char *p)
{
    memset(p, 0, POINT_ENTRY_BYTES_V4);
    batch_entry_pack(b, p);
    brt_put_le32(p + 80, b->instances);
    put_f32(p + 84, b->margin.condition);
    brt_put_le64(p + 88, b->instanced);
    put_f32(p + 96, b->margin.reach);
}

static void proto_entry_pack(const proto_entry *e, unsigned char *p)
{
    int a;
    memset(p, 0, PROTO_ENTRY_BYTES);
    brt_put_le64(p, e->offset);
    brt_put_le64(p + 8, e->size);
    brt_put_le64(p + 16, e->checksum);
    brt_put_le32(p + 24, e->triangles);
    for (a = 0; a < 3; a++) {
        put_f32(p + 28 + 4 * a, e->lo[a]);
        put_f32(p + 40 + 4 * a, e->hi[a]);
    }
}

static void proto_entry_unpack(const unsigned char *p, proto_entry *e)
{
    int a;
    e->offset = brt_get_le64(p);
    e->size = brt_get_le64(p + 8);
    e->checksum = brt_get_le64(p + 16);
    e->triangles = brt_get_le32(p + 24);
    for (a = 0; a < 3; a++) {
        e->lo[a] = get_f32(p + 28 + 4 * a);
        e->hi[a] = get_f32(p + 40 + 4 * a);
    }
}

static void batch_entry_unpack(const unsigned char *p, point_entry *b)
{
    int a;
    for (a = 0; a < 3; a++) {
        b->lo[a] = get_f32(p + 4 * a);
        b->hi[a] = get_f32(p + 12 + 4 * a);
        b->proxy.origin[a] = get_f32(p + 60 + 4 * a);
    }
    b->offset = brt_get_le64(p + 24);
    b->size = brt_get_le64(p + 32);
    b->checksum = brt_get_le64(p + 40);
    b->triangles = brt_get_le32(p + 48);
    b->proxy.root = brt_get_le32(p + 52);
    b->proxy.res = brt_get_le32(p + 56);
    b->proxy.cell = get_f32(p + 72);
    b->inner.root = brt_get_le32(p + 76);
    b->instances = 0;
    b->instanced = 0;
    memset(&b->margin, 0, sizeof b->margin);
}

static void top_node_pack(const top_node *n, unsigned char *p)
{
    int row, lane;
    for (row = 0; row < 6; row++)
        for (lane = 0; lane < 4; lane++) put_f32(p + 16 * row + 4 * lane, n->box[row][lane]);
    for (lane = 0; lane < 4; lane++) brt_put_le32(p + 96 + 4 * lane, n->child[lane]);
}

/* In memory the boxes are kept grown for brt_box_span4 (once, at open,
** instead of at every test); the file holds them exact. */
void brt_top_node_pad(top_node *n)
{
    int lane, a;
    for (lane = 0; lane < 4; lane++) {
        float lo[3], hi[3];
        if (n->child[lane] == TOP_EMPTY) continue;
        for (a = 0; a < 3; a++) {
            lo[a] = n->box[a][lane];
            hi[a] = n->box[3 + a][lane];
        }
        brt_box_pad(lo, hi, lo, hi);
        for (a = 0; a < 3; a++) {
            n->box[a][lane] = lo[a];
            n->box[3 + a][lane] = hi[a];
        }
    }
}

static void top_node_unpack(const unsigned char *p, top_node *n)
{
    int row, lane;
    for (row = 0; row < 6; row++)
        for (lane = 0; lane < 4; lane++) n->box[row][lane] = get_f32(p + 16 * row + 4 * lane);
    for (lane = 0; lane < 4; lane++) n->child[lane] = brt_get_le32(p + 96 + 4 * lane);
}

static int header_instanced(const scene_header *h)
{
    return h->prototype_count > 0;
}

static void header_pack(const scene_header *h, unsigned char *p)
{
    int s;
    memset(p, 0, SCENE_HEADER_BYTES);
    memcpy(p, SCENE_MAGIC, 8);
    brt_put_le32(p + 8, header_instanced(h) ? SCENE_VERSION_INSTANCED : SCENE_VERSION);
    brt_put_le32(p + 12, SCENE_ENDIAN_MARK);
    brt_put_le64(p + 16, h->stamp);
    brt_put_le32(p + 24, h->point_tris);
    brt_put_le32(p + 28, h->proxy_res);
    brt_put_le32(p + 32, h->point_count);
    brt_put_le32(p + 36, h->triangle_count);
    brt_put_le32(p + 40, h->top_node_count);
    brt_put_le64(p + 48, h->geometry_bytes);
    for (s = 0; s < 3; s++) {
        brt_put_le64(p + 56 + 24 * s, h->sections[s].offset);
        brt_put_le64(p + 64 + 24 * s, h->sections[s].size);
        brt_put_le64(p + 72 + 24 * s, h->sections[s].checksum);
    }
    if (header_instanced(h)) {
        brt_put_le32(p + 44, h->prototype_count);
        brt_put_le64(p + 128, h->sections[SECTION_PROTOTYPES].offset);
        brt_put_le64(p + 136, h->sections[SECTION_PROTOTYPES].size);
        brt_put_le64(p + 144, h->sections[SECTION_PROTOTYPES].checksum);
        brt_put_le32(p + 152, h->instance_count);
        put_f32(p + 156, h->margin.condition);
        put_f32(p + 160, h->margin.reach);
        put_f32(p + 176, h->margin.center[0]);
        put_f32(p + 180, h->margin.center[1]);
        put_f32(p + 184, h->margin.center[2]);
        brt_put_le64(p + 192, h->point_instanced);
        brt_put_le32(p + 200, h->instance_voxels);
        brt_put_le64(p + 168, h->instanced_triangles);
    }
    brt_put_le64(p + 248, brt_checksum64(p, 248));
}

/* Checks magic, endianness, version and checksum, in that order, so the
** message names the first thing that is wrong. */
static brt_result header_unpack(const char *path, const unsigned char *p, scene_header *h,
                                brt_error *err)
{
    uint32_t mark = brt_get_le32(p + 12), version = brt_get_le32(p + 8);
    int s;
    if (memcmp(p, SCENE_MAGIC, 8) != 0)
        return brt_fail(err, BRT_EFORMAT, "%s: not a batchrt scene file (bad magic)", path);
    if (mark != SCENE_ENDIAN_MARK)
        return brt_fail(err, BRT_EFORMAT, "%s: a version-1 scene file written on a machine of the other "
                        "byte order (delete the file to rebuild it)", path);
    if (version != SCENE_VERSION && version != SCENE_VERSION_INSTANCED)
        return brt_fail(err, BRT_EFORMAT, "%s: scene file version %u, this build reads versions "
                        "%u and %u (delete the file to rebuild it)", path, version, SCENE_VERSION,
                        SCENE_VERSION_INSTANCED);
    if (brt_get_le64(p + 248) != brt_checksum64(p, 248))
        return brt_fail(err, BRT_EFORMAT, "%s: header checksum mismatch (corrupt file)", path);
    h->stamp = brt_get_le64(p + 16);
    h->point_tris = brt_get_le32(p + 24);
    h->proxy_res = brt_get_le32(p + 28);
    h->point_count = brt_get_le32(p + 32);
    h->triangle_count = brt_get_le32(p + 36);
    h->top_node_count = brt_get_le32(p + 40);
    h->geometry_bytes = brt_get_le64(p + 48);
    for (s = 0; s < 3; s++) {
        h->sections[s].offset = brt_get_le64(p + 56 + 24 * s);
        h->sections[s].size = brt_get_le64(p + 64 + 24 * s);
        h->sections[s].checksum = brt_get_le64(p + 72 + 24 * s);
    }
    memset(&h->sections[SECTION_PROTOTYPES], 0, sizeof h->sections[SECTION_PROTOTYPES]);
    h->prototype_count = h->instance_count = 0;
    h->instanced_triangles = 0;
    memset(&h->margin, 0, sizeof h->margin);
    h->point_instanced = 0;
    h->instance_voxels = 0;
    if (version == SCENE_VERSION_INSTANCED) {
        h->prototype_count = brt_get_le32(p + 44);
        h->sections[SECTION_PROTOTYPES].offset = brt_get_le64(p + 128);
        h->sections[SECTION_PROTOTYPES].size = brt_get_le64(p + 136);
        h->sections[SECTION_PROTOTYPES].checksum = brt_get_le64(p + 144);
        h->instance_count = brt_get_le32(p + 152);
        h->margin.condition = get_f32(p + 156);
        h->margin.reach = get_f32(p + 160);
        h->margin.center[0] = get_f32(p + 176);
        h->margin.center[1] = get_f32(p + 180);
        h->margin.center[2] = get_f32(p + 184);
        h->point_instanced = brt_get_le64(p + 192);
        h->instance_voxels = brt_get_le32(p + 200);
        h->instanced_triangles = brt_get_le64(p + 168);
        if (h->prototype_count == 0)
            return brt_fail(err, BRT_EFORMAT, "%s: header: version 4 without prototypes", path);
    }
    return BRT_OK;
}

static brt_result write_at(int fd, const void *data, size_t size, uint64_t offset,
                           const char *path, brt_error *err)
{
    if (brt_write_fully(fd, data, size, (int64_t)offset) != 0)
        return brt_fail(err, BRT_EIO, "%s: cannot write: %s", path, strerror(errno));
    return BRT_OK;
}

/* ---- building a scene file out of core ------------------------------- */
/*
** The build never holds the triangles: it spills them to a temporary file
** and works through it in buckets of at most bucket_tris triangles.
**
**   pass A  runs the triangle source once: each triangle becomes a 40-byte
**           record (its 9 floats and its number) appended to the spill
**           file in stream order, and the bounds of the centroids grow.
**           (One run: parsing an OBJ costs far more than reading 40 bytes
**           per triangle back, so the source is not run again.)
**   split   a run of records larger than a bucket is split spatially: a
**           histogram of its centroids over 2^21 Morton cells (7 bits per
**           axis of its own centroid bounds) is counted in one read, cells
**           are packed in Morton order into children of at most
**           bucket_tris triangles (a cell with more is a child on its own),
**           and a second read scatters each record to its child's region,
**           appended to the spill file (the counts give every region its
**           place, so no chunk lists are needed), through one write buffer
**           per child.  Children larger than a bucket are split again; a
**           run whose records all fall in one cell (equal centroids, or
**           bounds that overflow) is cut in record order instead, so every
**           split makes progress.  A child larger than a bucket is one
**           cell, whose centroids span at most 1/128 of its parent's extent
**           per axis, so within about 40 levels (floats span 2^277) a run
**           is small enough or flat.  Records keep stream order in every
**           region, so the number order of a bucket is its record order.
**   build   a bucket is read whole and split in memory by the median
**           splits above into batching points of at most point_tris
**           triangles; each gets its BVH blob, written at the next page of
**           the scene file, its proxy in the shared DAG, and a table entry.
**           A mesh that fits one bucket is partitioned exactly as a whole
**           in-memory median split would (the same file as before).
**   tables  the top-level BVH, the point table and the DAG, then the header
**           (format unchanged).
**
** Held in memory, whatever the triangle count: the histogram (8 MiB), one
** bucket (bucket_tris records, centroids and ids: 56 bytes each, 86 MiB at
** most by default), one batching point's arrays and BVH build, one proxy
** grid, the scatter buffers (16 MiB together) and one read chunk; plus the
** per-point tables (batch entries, boxes, the DAG) and, in pass A, what the
** source holds (a mesh file's vertex positions).  The spill file takes 40
** bytes per triangle for pass A and 40 more per split level (usually one).
** It is unlinked as soon as it is created, so it disappears with its
** descriptor on success, on failure, on interrupt and if the process dies.
** The interrupt flag is polled once per chunk and per batching point.
*/
#define CELL_COUNT (1u << (3 * CELL_BITS))          /* Morton cells of a split */
#define NO_CHILD 0xFFFFFFFFu

typedef struct spill_record {
    float v[9];                 /* the corners v0, v1, v2 */
    uint32_t prim;              /* the triangle's number */
} spill_record;

typedef char spill_record_has_no_padding[sizeof(spill_record) == 40 ? 1 : -1];

/* A run of records in the spill file and the bounds of their centroids. */
typedef struct bucket {
    uint64_t first;             /* index of its first record */
    uint32_t count;
    float lo[3], hi[3];
} bucket;

/* A bucket being written: records go through buf (cap of them). */
typedef struct spill_out {
    bucket b;                   /* count: records written or buffered */
    spill_record *buf;
    uint32_t held, cap;
} spill_out;

static void scene_options_resolve(const brt_scene_options *opt, uint32_t *point_tris,
                                  uint32_t *res)
{
    *point_tris = opt && opt->point_tris ? opt->point_tris : 100000;
    *res = opt && opt->proxy_res ? opt->proxy_res : 128;
}

/* How the options voxelize instances (INSTANCE_VOXELS_*). */
static int scene_options_instance_voxels(const brt_scene_options *opt)
{
    return opt && opt->exact_voxels ? INSTANCE_VOXELS_EVERY_TRIANGLE : INSTANCE_VOXELS_PRUNED;
}

/* Everything written while a scene file is built. */
typedef struct scene_writer {
    const char *path;           /* final name, for messages */
    int fd;
    uint64_t offset;            /* next free, page-aligned */
    uint32_t res;
    int instance_voxels;        /* INSTANCE_VOXELS_*: brt_scene_options.exact_voxels */
    brt_svdag *dag;
    point_entry *points;       /* the per-point tables, grown as points come */
    float *boxes;               /* 6 floats per batching point */
    uint32_t point_count;
    size_t point_cap;
    uint64_t geometry_bytes;
} scene_writer;

struct instance_build;

typedef struct scene_builder {
    scene_writer w;
    int spill_fd;
    uint64_t spill_end;         /* records in the spill file */
    const volatile sig_atomic_t *interrupt;
    uint32_t point_tris, bucket_tris, chunk;
    uint32_t instance_bucket;   /* instances of one bucket of the instance pass */
    uint64_t point_instanced;   /* brt_scene_options.point_instanced */
    /* What a bucket that fits is made into: build_bucket (triangles), or
    ** instance_bucket (the instance pass, "instance points"). */
    brt_result (*leaf)(struct scene_builder *b, const bucket *bk, brt_error *err);
    int instance_fd;            /* the instance pass's records, by slot */
    struct instance_build *ib;
    spill_out root;             /* pass A's output: the whole stream */
    spill_record *read_buf;     /* chunk records */
    uint32_t *cells;            /* CELL_COUNT: a histogram, then each cell's child */
    spill_record *records;      /* one bucket in memory, with its centroids */
    float *centroids;           /* and median split order */
    uint32_t *order;
    partition points;           /* the bucket's batching points */
    uint32_t *indices;          /* 0, 1, 2, ...: a point's triangles are its corners */
    brt_pool pool;                  /* brt_scene_options.threads */
    struct point_work *work;    /* a window of points built at once */
    uint32_t window;
    brt_solids *solids;         /* the bucket's closed components (svdag.c) */
} scene_builder;

static brt_result poll_interrupt(const scene_builder *b, brt_error *err)
{
    if (b->interrupt && *b->interrupt)
        return brt_fail(err, BRT_EINTR, "%s: build interrupted", b->w.path);
    return BRT_OK;
}

static void centroid(const spill_record *r, float c[3])
{
    int a;
    for (a = 0; a < 3; a++) c[a] = (r->v[a] + r->v[3 + a] + r->v[6 + a]) / 3.0f;
}

static void bounds_clear(float lo[3], float hi[3])
{
    int a;
    for (a = 0; a < 3; a++) {
        lo[a] = INFINITY;
        hi[a] = -INFINITY;
    }
}

void brt_bounds_grow(float lo[3], float hi[3], const float p[3])
{
    int a;
    for (a = 0; a < 3; a++) {
        if (p[a] < lo[a]) lo[a] = p[a];
        if (p[a] > hi[a]) hi[a] = p[a];
    }
}

/* ---- the spill file ---- */

static brt_result spill_write(scene_builder *b, const spill_record *recs, uint32_t n,
                              uint64_t first, brt_error *err)
{
    if (brt_write_fully(b->spill_fd, recs, (size_t)n * sizeof *recs,
                    (int64_t)(first * sizeof *recs)) != 0)
        return brt_fail(err, BRT_EIO, "%s: cannot write: %s", b->w.path, strerror(errno));
    return BRT_OK;
}

static brt_result spill_read(scene_builder *b, spill_record *recs, uint32_t n, uint64_t first,
                             brt_error *err)
{
    return brt_read_fully(b->spill_fd, recs, (size_t)n * sizeof *recs, first * sizeof *recs,
                      brt_pread_reader, NULL, NULL, b->w.path, err);
}

/* Writes the buffered records at the end of the bucket's region. */
static brt_result spill_flush(scene_builder *b, spill_out *o, brt_error *err)
{
    brt_result r = spill_write(b, o->buf, o->held, o->b.first + o->b.count - o->held, err);
    o->held = 0;
    return r;
}

static brt_result spill_put(scene_builder *b, spill_out *o, const spill_record *rec,
                            const float c[3], brt_error *err)
{
    o->buf[o->held++] = *rec;
    o->b.count++;
    brt_bounds_grow(o->b.lo, o->b.hi, c);
    return o->held == o->cap ? spill_flush(b, o, err) : BRT_OK;
}

/* Pass A's consumer: the chunk in stream order onto the root bucket. */
static brt_result spill_stream(void *user, const float *corners, uint32_t count, uint32_t first,
                               brt_error *err)
{
    scene_builder *b = user;
    uint32_t i;
    brt_result r = poll_interrupt(b, err);
    if (r != BRT_OK) return r;
    if (first != b->root.b.count)
        return brt_fail(err, BRT_EARG, "%s: the triangle source numbered a chunk %u, not %u",
                        b->w.path, first, b->root.b.count);
    if (count > MAX_COUNT - b->root.b.count)
        return brt_fail(err, BRT_EARG, "%s: more than %u triangles", b->w.path, MAX_COUNT);
    for (i = 0; i < count && r == BRT_OK; i++) {
        spill_record rec;
        float c[3];
        memcpy(rec.v, corners + 9 * (size_t)i, sizeof rec.v);
        rec.prim = first + i;
        centroid(&rec, c);
        r = spill_put(b, &b->root, &rec, c, err);
    }
    return r;
}

/* Calls fn on every record of bucket in order, a chunk at a time. */
typedef brt_result (*record_fn)(scene_builder *b, const spill_record *rec, void *user,
                                brt_error *err);

static brt_result for_each_record(scene_builder *b, const bucket *bk, record_fn fn, void *user,
                                  brt_error *err)
{
    uint32_t done = 0, i;
    brt_result r = BRT_OK;
    while (done < bk->count && r == BRT_OK) {
        uint32_t n = bk->count - done < b->chunk ? bk->count - done : b->chunk;
        if ((r = poll_interrupt(b, err)) != BRT_OK) break;
        r = spill_read(b, b->read_buf, n, bk->first + done, err);
        for (i = 0; i < n && r == BRT_OK; i++) r = fn(b, &b->read_buf[i], user, err);
        done += n;
    }
    return r;
}

/* ---- splitting a bucket larger than memory allows ---- */

/* Quantises centroids in a bucket's centroid bounds: 2^bits cells per
** axis, bits = CELL_BITS, or fewer for a bucket of fewer than 2^(3 bits)
** / 4 records (more cells than records would only cost time: the small
** buckets of the tests).  A flat axis, an extent that overflows or a NaN
** lands in cell 0, so the code is always in range. */
typedef struct cell_frame {
    float lo[3], scale[3];
    int bits;
    uint32_t cells;             /* 2^(3 bits) */
} cell_frame;

static void cell_frame_init(const bucket *bk, cell_frame *f)
{
    int a;
    for (f->bits = CELL_BITS; f->bits > 1 && (1u << (3 * f->bits)) / 4 > bk->count; f->bits--) {}
    f->cells = 1u << (3 * f->bits);
    for (a = 0; a < 3; a++) {
        float extent = bk->hi[a] - bk->lo[a];
        f->lo[a] = bk->lo[a];
        f->scale[a] = extent > 0.0f ? (float)(1u << f->bits) / extent : 0.0f;
    }
}

/* Spreads the low 10 bits of v to every third bit (bit i to bit 3i). */
static uint32_t spread3(uint32_t v)
{
    v = (v | (v << 16)) & 0x030000FFu;
    v = (v | (v << 8)) & 0x0300F00Fu;
    v = (v | (v << 4)) & 0x030C30C3u;
    return (v | (v << 2)) & 0x09249249u;
}

/* The Morton code of the cell (bits of x, y, z interleaved). */
static uint32_t cell_of(const cell_frame *f, const spill_record *rec)
{
    float c[3];
    uint32_t q[3];
    int a;
    centroid(rec, c);
    for (a = 0; a < 3; a++) {
        float x = (c[a] - f->lo[a]) * f->scale[a];
        q[a] = x > 0.0f ? (x < (float)(1u << f->bits) ? (uint32_t)x : (1u << f->bits) - 1) : 0;
    }
    return spread3(q[0]) | spread3(q[1]) << 1 | spread3(q[2]) << 2;
}

typedef struct split_state {
    cell_frame frame;
    spill_out *children;
} split_state;

static brt_result count_cell(scene_builder *b, const spill_record *rec, void *user,
                             brt_error *err)
{
    (void)err;
    b->cells[cell_of(&((split_state *)user)->frame, rec)]++;
    return BRT_OK;
}

static brt_result scatter_record(scene_builder *b, const spill_record *rec, void *user,
                                 brt_error *err)
{
    split_state *s = user;
    float c[3];
    centroid(rec, c);
    return spill_put(b, &s->children[b->cells[cell_of(&s->frame, rec)]], rec, c, err);
}

/* Packs the histogram's cells in Morton order into children of at most
** bucket_tris records (a fuller cell alone), turning each cell's count
** into its child's index; the children's regions follow the spill file's
** end.  Returns the number of children (*planned their sizes). */
static uint32_t plan_children(scene_builder *b, uint32_t cells, uint32_t *sizes)
{
    uint32_t cell, children = 0, open = 0;
    for (cell = 0; cell < cells; cell++) {
        uint32_t n = b->cells[cell];
        if (n == 0) {
            b->cells[cell] = NO_CHILD;
            continue;
        }
        if (children == 0 || open + n > b->bucket_tris) {
            sizes[children++] = 0;
            open = 0;
        }
        open += n;
        sizes[children - 1] += n;
        b->cells[cell] = children - 1;
    }
    return children;
}

static brt_result build_bucket(scene_builder *b, const bucket *bk, brt_error *err);
static brt_result process_bucket(scene_builder *b, const bucket *bk, brt_error *err);

/* A bucket whose records share one cell: runs of bucket_tris in record order. */
static brt_result cut_in_order(scene_builder *b, const bucket *bk, brt_error *err)
{
    bucket part = *bk;
    uint32_t done;
    brt_result r = BRT_OK;
    for (done = 0; done < bk->count && r == BRT_OK; done += part.count) {
        part.first = bk->first + done;
        part.count = bk->count - done < b->bucket_tris ? bk->count - done : b->bucket_tris;
        r = b->leaf(b, &part, err);
    }
    return r;
}

/* Scatters the bucket into its planned children, then processes them. */
static brt_result scatter(scene_builder *b, const bucket *bk, split_state *s, const uint32_t *sizes,
                          uint32_t children, brt_error *err)
{
    uint32_t cap = (uint32_t)(SCATTER_BYTES / sizeof(spill_record) / children), i;
    spill_record *bufs;
    brt_result r = BRT_OK;
    if (cap > b->chunk) cap = b->chunk;
    if (cap == 0) cap = 1;
    bufs = malloc((size_t)children * cap * sizeof *bufs);
    if (!bufs) return brt_fail(err, BRT_ENOMEM, "%s: out of memory", b->w.path);
    for (i = 0; i < children; i++) {
        spill_out *o = &s->children[i];
        o->b.first = b->spill_end;
        o->b.count = 0;
        bounds_clear(o->b.lo, o->b.hi);
        o->buf = bufs + (size_t)i * cap;
        o->held = 0;
        o->cap = cap;
        b->spill_end += sizes[i];
    }
    r = for_each_record(b, bk, scatter_record, s, err);
    for (i = 0; i < children && r == BRT_OK; i++) r = spill_flush(b, &s->children[i], err);
    free(bufs);
    for (i = 0; i < children && r == BRT_OK; i++) r = process_bucket(b, &s->children[i].b, err);
    return r;
}

static brt_result split_bucket(scene_builder *b, const bucket *bk, brt_error *err)
{
    split_state s;
    uint32_t *sizes, largest = 0, i;
    brt_result r;
    if (!b->cells && !(b->cells = malloc(CELL_COUNT * sizeof *b->cells)))
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", b->w.path);
    cell_frame_init(bk, &s.frame);
    memset(b->cells, 0, s.frame.cells * sizeof *b->cells);
    r = for_each_record(b, bk, count_cell, &s, err);
    if (r != BRT_OK) return r;
    for (i = 0; i < s.frame.cells; i++)
        if (b->cells[i] > largest) largest = b->cells[i];
    if (largest == bk->count) return cut_in_order(b, bk, err);
    sizes = malloc(((size_t)bk->count / b->bucket_tris * 2 + 2) * sizeof *sizes);
    s.children = sizes ? malloc(((size_t)bk->count / b->bucket_tris * 2 + 2) * sizeof *s.children) : NULL;
    if (!s.children) r = brt_fail(err, BRT_ENOMEM, "%s: out of memory", b->w.path);
    else r = scatter(b, bk, &s, sizes, plan_children(b, s.frame.cells, sizes), err);
    free(sizes);
    free(s.children);
    return r;
}

static brt_result process_bucket(scene_builder *b, const bucket *bk, brt_error *err)
{
    return bk->count <= b->bucket_tris ? b->leaf(b, bk, err) : split_bucket(b, bk, err);
}

/* ---- batching points ---- */

/* A new entry of the per-point tables. */
static point_entry *point_append(scene_writer *w)
{
    if (w->point_count == w->point_cap) {
        size_t need = (size_t)w->point_count + 1, cap = w->point_cap, box_cap = w->point_cap;
        point_entry *points = brt_grow(w->points, &cap, need, sizeof *points);
        float *boxes;
        if (points) w->points = points;
        boxes = points ? brt_grow(w->boxes, &box_cap, need, 6 * sizeof *boxes) : NULL;
        if (!boxes || need > MAX_COUNT) return NULL;
        w->boxes = boxes;
        w->point_cap = cap;         /* box_cap too: both grew from point_cap to need */
    }
    memset(&w->points[w->point_count], 0, sizeof *w->points);
    return &w->points[w->point_count++];
}

/*
** Threads: a bucket's points are built a window at a time (two per
** thread).  Each point is built whole by one thread into a work slot of
** its own -- its triangles, box, BVH blob and checksum, and its proxy's
** voxel grid -- and the caller writes the blobs and adds the grids to the
** shared DAG in point order, each as soon as the points before it are
** written (brt_pool_run's commit).  So blob offsets and the DAG's nodes, whose
** numbers follow the order of the adds, are those of one thread.
*/
typedef struct point_work {
    float *corners;             /* its triangles: 9 floats each */
    uint32_t *prims;            /* and the number of each */
    uint32_t first, count;      /* its records: order[first .. first + count) */
    float lo[3], hi[3];
    void *blob;                 /* its BVH, as stored */
    size_t size;
    uint64_t checksum;
    brt_grid grid;              /* its proxy's voxels */
    brt_result bvh_result, grid_result;
    brt_grid inner;             /* its inner proxy's voxels (svdag.c) */
} point_work;

/* Builds one point in its slot (any thread: reads the bucket only). */
static void point_build(const scene_builder *b, point_work *pw)
{
    brt_bvh *bvh = NULL;
    uint32_t i;
    bounds_clear(pw->lo, pw->hi);
    for (i = 0; i < pw->count; i++) {
        const spill_record *rec = &b->records[b->order[pw->first + i]];
        memcpy(pw->corners + 9 * (size_t)i, rec->v, sizeof rec->v);
        pw->prims[i] = rec->prim;
        brt_bounds_grow(pw->lo, pw->hi, rec->v);
        brt_bounds_grow(pw->lo, pw->hi, rec->v + 3);
        brt_bounds_grow(pw->lo, pw->hi, rec->v + 6);
    }
    pw->blob = NULL;
    pw->bvh_result = brt_bvh_build(pw->corners, b->indices, pw->count, pw->prims, &bvh);
    if (pw->bvh_result == BRT_OK) {
        pw->size = brt_bvh_blob_size(bvh);
        pw->blob = calloc(1, pw->size ? pw->size : 1);
        if (pw->blob) brt_bvh_blob_write(bvh, pw->blob);
        if (pw->blob) pw->checksum = brt_checksum64(pw->blob, pw->size);
        brt_bvh_free(bvh);
    }
    pw->grid_result = brt_grid_init(&pw->grid, pw->lo, pw->hi, b->w.res);
    if (pw->grid_result == BRT_OK)
        pw->grid_result = brt_voxelize(&pw->grid, pw->corners, b->indices, pw->count);
    pw->inner.bits = NULL;
    if (pw->grid_result == BRT_OK)
        pw->grid_result = brt_grid_init(&pw->inner, pw->lo, pw->hi, inner_res(b->w.res));
    if (pw->grid_result == BRT_OK)
        pw->grid_result = brt_voxelize_inner(&pw->inner, b->solids);
}

/* Writes one built point: its blob at the next page, its table entry and
** box, its proxy added to the shared pool (the caller, in point order). */
static brt_result point_write(scene_builder *b, point_work *pw, brt_error *err)
{
    scene_writer *w = &b->w;
    point_entry *e;
    brt_result r = poll_interrupt(b, err);
    if (r != BRT_OK) return r;
    if (pw->bvh_result != BRT_OK)
        return brt_fail(err, pw->bvh_result, "%s: building a batching point's BVH: %s",
                        w->path, brt_result_string(pw->bvh_result));
    if (!pw->blob || !(e = point_append(w))) return brt_fail(err, BRT_ENOMEM, "%s: out of memory", w->path);
    memcpy(e->lo, pw->lo, sizeof e->lo);
    memcpy(e->hi, pw->hi, sizeof e->hi);
    e->triangles = pw->count;
    e->size = pw->size;
    e->checksum = pw->checksum;
    e->offset = w->offset;
    if ((r = write_at(w->fd, pw->blob, pw->size, e->offset, w->path, err)) != BRT_OK) return r;
    w->offset = brt_round_up_page(e->offset + e->size);
    w->geometry_bytes += e->size;
    memcpy(w->boxes + 6 * (size_t)(w->point_count - 1), e->lo, 3 * sizeof(float));
    memcpy(w->boxes + 6 * (size_t)(w->point_count - 1) + 3, e->hi, 3 * sizeof(float));
    r = pw->grid_result;
    if (r == BRT_OK) r = brt_svdag_add(w->dag, &pw->grid, &e->proxy);
    if (r == BRT_OK) r = brt_svdag_add(w->dag, &pw->inner, &e->inner);
    if (r != BRT_OK) return brt_fail(err, r, "%s: building a proxy: %s", w->path, brt_result_string(r));
    return BRT_OK;
}

typedef struct window_job {
    scene_builder *b;
    brt_result result;
    brt_error *err;
} window_job;

static void window_build(void *ctx, unsigned thread, size_t first, size_t end)
{
    const window_job *j = ctx;
    size_t k;
    (void)thread;
    for (k = first; k < end; k++) point_build(j->b, &j->b->work[k]);
}

static void window_write(void *ctx, size_t first, size_t end)
{
    window_job *j = ctx;
    size_t k;
    for (k = first; k < end; k++) {
        point_work *pw = &j->b->work[k];
        if (j->result == BRT_OK) j->result = point_write(j->b, pw, j->err);
        free(pw->blob);
        pw->blob = NULL;
        brt_grid_free(&pw->grid);
        brt_grid_free(&pw->inner);
    }
}

/* A bucket that fits in memory: read whole, split by medians into
** batching points (ties by record order, which is number order), built
** a window at a time.  Its closed components are found over the whole
** bucket, so a solid that batching points cut still gives each of them
** inner voxels (svdag.c, "Inner proxies"). */
static brt_result build_bucket(scene_builder *b, const bucket *bk, brt_error *err)
{
    uint32_t i, k, m;
    window_job j;
    brt_result r = spill_read(b, b->records, bk->count, bk->first, err);
    if (r != BRT_OK) return r;
    for (i = 0; i < bk->count; i++) {
        centroid(&b->records[i], b->centroids + 3 * (size_t)i);
        b->order[i] = i;
    }
    b->points.count = 0;
    b->points.order = b->order;
    if (brt_partition_split(&b->points, b->centroids, 0, bk->count, b->point_tris) != BRT_OK ||
        brt_solids_build(b->records[0].v, sizeof *b->records / sizeof(float), bk->count,
                         &b->solids) != BRT_OK)
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", b->w.path);
    j.b = b;
    j.err = err;
    j.result = BRT_OK;
    for (i = 0; i < b->points.count && j.result == BRT_OK; i += m) {
        m = b->points.count - i < b->window ? b->points.count - i : b->window;
        for (k = 0; k < m; k++) {
            b->work[k].first = b->points.ranges[i + k].first;
            b->work[k].count = b->points.ranges[i + k].count;
        }
        brt_pool_run(&b->pool, window_build, window_write, &j, m, 1);
    }
    brt_solids_free(b->solids);
    b->solids = NULL;
    return j.result;
}

/* ---- instance points ---- */
/*
** An instanced scene (brt_scene_build_source) gets, after the batching
** points of its world triangles, the blobs of its prototypes (one BVH
** each, written once) and batching points of instances, cut a bucket at
** a time by brt_partition_by_size (the instance pass, below); each point's
** blob is its instance table:
**   0 "BRTINSTS"  8 u32 instances n  12 u32 tree nodes m  16 u32
**   distinct prototypes k  20 u32 0  24 u64 instanced triangles
**   32 k u32 prototype ids, ascending, then zeros to a multiple of 8
**   n records of INSTANCE_RECORD_BYTES: u32 instance number, u32 prototype,
**     f32 xform[12]
**   m tree nodes of 16 bytes: u32 child[4] (TOP_EMPTY, a node index, or
**     TOP_LEAF | record), the 4-wide tree of brt_top_build over the
**     instances' world boxes
** The tree's boxes are not stored: a load recomputes them from the
** instances and the prototypes' boxes (brt_instance_table_open), so no table,
** however forged, can make the tree prune a hit.  Its proxy voxelizes
** every instance by descending its prototype's BVH (brt_voxelize_
** instance), dilated by INSTANCE_DILATION of a voxel: the rounding of a
** ray's transform that the proxy admits (proxy_admits).
*/
#define INSTANCE_TABLE_MAGIC "BRTINSTS"
#define INSTANCE_TABLE_HEADER 32
#define INSTANCE_RECORD_BYTES 56
#define INSTANCE_NODE_BYTES 16
#define SET_MAX_DEPTH 20   /* a stored tree deeper than this is refused: SET_STACK */

static size_t instance_table_bytes(uint32_t n, uint32_t m, uint32_t k)
{
    return INSTANCE_TABLE_HEADER + ((size_t)k * 4 + 7) / 8 * 8 + (size_t)n * INSTANCE_RECORD_BYTES +
           (size_t)m * INSTANCE_NODE_BYTES;
}

/* A batching point of instances, as the build holds it before writing. */
typedef struct instance_point {
    const brt_instance *items;  /* the bucket's instances, by local slot */
    const uint32_t *numbers;
    const uint32_t *slots;      /* this point's n slots */
    uint32_t n;
    const top_node *nodes;      /* its tree, over its records 0 .. n - 1 */
    uint32_t m;
    const uint32_t *uses;       /* its distinct prototypes, ascending */
    uint32_t k;
    uint64_t instanced;
} instance_point;

static void instance_table_pack(const instance_point *ip, unsigned char *p)
{
    size_t at = INSTANCE_TABLE_HEADER;
    uint32_t i;
    int a;
    memset(p, 0, instance_table_bytes(ip->n, ip->m, ip->k));
    memcpy(p, INSTANCE_TABLE_MAGIC, 8);
    brt_put_le32(p + 8, ip->n);
    brt_put_le32(p + 12, ip->m);
    brt_put_le32(p + 16, ip->k);
    brt_put_le64(p + 24, ip->instanced);
    for (i = 0; i < ip->k; i++, at += 4) brt_put_le32(p + at, ip->uses[i]);
    at = (at + 7) / 8 * 8;
    for (i = 0; i < ip->n; i++, at += INSTANCE_RECORD_BYTES) {
        const brt_instance *in = &ip->items[ip->slots[i]];
        brt_put_le32(p + at, ip->numbers[ip->slots[i]]);
        brt_put_le32(p + at + 4, in->prototype);
        for (a = 0; a < 12; a++) put_f32(p + at + 8 + 4 * a, in->xform[a]);
    }
    for (i = 0; i < ip->m; i++, at += INSTANCE_NODE_BYTES)
        for (a = 0; a < 4; a++) brt_put_le32(p + at + 4 * a, ip->nodes[i].child[a]);
}

/* The instance pass.  Pass A of the instances: each instance, checked,
** becomes an INSTANCE_DATA_BYTES record of the instance file (its number,
** prototype, transform and radius) at its slot -- the instances of non-
** empty prototypes, numbered in stream order -- and a 40-byte spill record
** whose three corners are the centre of its world box and whose number is
** its slot.  The spill records then go through the buckets of the
** triangles (split by Morton cells, scattered), so that a bucket holds the
** instances of one region; each bucket that fits (instance_bucket) reads
** its slots' records back and is cut into batching points in memory.  So
** the build holds one bucket of instances (at most bucket_tris / 4: 96
** bytes of arrays and a spill record each), never all of them.
*/
#define INSTANCE_DATA_BYTES 64

typedef struct instance_build {
    /* one bucket, by its local slot */
    brt_instance *items;
    uint32_t *numbers;
    float *boxes, *centres, *radii; /* 6, 3 and 1 floats each */
    uint32_t count, cap;
    spill_record *recs;             /* the bucket's spill records */
    /* the whole scene */
    uint32_t streamed, slots;       /* instances streamed; slots (non-empty prototypes) */
    brt_bvh **protos;               /* every prototype's BVH, for the proxies */
    proto_entry *entries;           /* the prototype table */
    uint32_t proto_count;
    uint32_t *stamp, stamp_now;     /* instance_range_size's marks, per prototype */
    uint64_t instanced;             /* instanced triangles of the whole scene */
    float condition, radius;        /* the largest: the walk's margin (scene_margin) */
    double dlo[3], dhi[3];          /* the bounds of the translations */
    spill_out root;                 /* pass A's spill records */
} instance_build;

/* The centre of an instance's world box (and box and radius). */
static void instance_box(const instance_build *ib, const brt_instance *in,
                         const brt_instance_frame *f, float box[6], float centre[3], float *radius)
{
    const proto_entry *pe = &ib->entries[in->prototype];
    int a;
    brt_instance_bounds(in, f, pe->lo, pe->hi, box, box + 3, radius);
    for (a = 0; a < 3; a++) centre[a] = 0.5f * box[a] + 0.5f * box[3 + a];
}

static brt_result spill_instance(scene_builder *b, instance_build *ib, const brt_instance *in,
                                 uint32_t number, brt_error *err)
{
    brt_instance_frame frame;
    unsigned char data[INSTANCE_DATA_BYTES];
    spill_record rec;
    float box[6], c[3], radius;
    brt_result r;
    int a;
    if ((r = brt_instance_admit(in, number, ib->proto_count, &frame, err)) != BRT_OK) return r;
    ib->instanced += ib->entries[in->prototype].triangles;
    if (ib->entries[in->prototype].triangles == 0) return BRT_OK;   /* in no batching point */
    if (ib->slots == MAX_COUNT)
        return brt_fail(err, BRT_EARG, "%s: more than %u instances", b->w.path, MAX_COUNT);
    instance_box(ib, in, &frame, box, c, &radius);
    memset(data, 0, sizeof data);
    brt_put_le32(data, number);
    brt_put_le32(data + 4, in->prototype);
    for (a = 0; a < 12; a++) put_f32(data + 8 + 4 * a, in->xform[a]);
    put_f32(data + 56, radius);
    if (brt_write_fully(b->instance_fd, data, sizeof data, (int64_t)ib->slots * INSTANCE_DATA_BYTES) != 0)
        return brt_fail(err, BRT_EIO, "%s: cannot write: %s", b->w.path, strerror(errno));
    for (a = 0; a < 3; a++) {
        rec.v[a] = rec.v[3 + a] = rec.v[6 + a] = c[a];
        if (frame.translation[a] < ib->dlo[a]) ib->dlo[a] = frame.translation[a];
        if (frame.translation[a] > ib->dhi[a]) ib->dhi[a] = frame.translation[a];
    }
    if (frame.condition > ib->condition) ib->condition = frame.condition;
    if (radius > ib->radius) ib->radius = radius;
    rec.prim = ib->slots++;
    return spill_put(b, &ib->root, &rec, c, err);
}

static brt_result spill_instances(void *user, const brt_instance *instances, uint32_t count,
                                  uint32_t first, brt_error *err)
{
    scene_builder *b = user;
    instance_build *ib = b->ib;
    uint32_t i;
    brt_result r = poll_interrupt(b, err);
    if (r == BRT_OK && (first != ib->streamed || count > UINT32_MAX - 1 - first))
        r = brt_fail(err, BRT_EARG, "instance stream: chunk numbered %u after %u instances",
                     (unsigned)first, (unsigned)ib->streamed);
    for (i = 0; i < count && r == BRT_OK; i++, ib->streamed++)
        r = spill_instance(b, ib, &instances[i], first + i, err);
    return r;
}

/* Reads a bucket's instances back into the arrays, by local slot. */
static brt_result instance_bucket_read(scene_builder *b, instance_build *ib, const bucket *bk,
                                       brt_error *err)
{
    uint32_t i;
    brt_result r = spill_read(b, ib->recs, bk->count, bk->first, err);
    for (i = 0; i < bk->count && r == BRT_OK; i++) {
        unsigned char data[INSTANCE_DATA_BYTES];
        brt_instance_frame frame;
        int a;
        r = brt_read_fully(b->instance_fd, data, sizeof data,
                       (uint64_t)ib->recs[i].prim * INSTANCE_DATA_BYTES, brt_pread_reader, NULL, NULL,
                       b->w.path, err);
        if (r != BRT_OK) break;
        ib->numbers[i] = brt_get_le32(data);
        ib->items[i].prototype = brt_get_le32(data + 4);
        for (a = 0; a < 12; a++) ib->items[i].xform[a] = get_f32(data + 8 + 4 * a);
        if (brt_instance_frame_init(&ib->items[i], ib->numbers[i], &frame, err) != BRT_OK)
            return BRT_EIO;   /* the instance file changed under the build */
        instance_box(ib, &ib->items[i], &frame, ib->boxes + 6 * (size_t)i, ib->centres + 3 * (size_t)i,
                     &ib->radii[i]);
    }
    ib->count = bk->count;
    return r;
}

/* range_size_fn: the distinct prototypes' triangles of some slots. */
static uint64_t instance_range_size(void *user, const uint32_t *slots, uint32_t n, uint32_t *distinct,
                                    uint64_t *instanced)
{
    instance_build *ib = user;
    uint64_t size = 0;
    uint32_t i;
    *distinct = 0;
    *instanced = 0;
    ib->stamp_now++;
    for (i = 0; i < n; i++) {
        const uint32_t p = ib->items[slots[i]].prototype;
        *instanced += ib->entries[p].triangles;
        if (ib->stamp[p] == ib->stamp_now) continue;
        ib->stamp[p] = ib->stamp_now;
        size += ib->entries[p].triangles;
        ++*distinct;
    }
    return size;
}

/* Writes the prototypes' blobs and fills the prototype table, keeping
** each BVH for the proxies of the points of instances. */
static brt_result build_prototypes(scene_builder *b, const brt_scene_source *source,
                                   instance_build *ib, brt_error *err)
{
    uint32_t p;
    for (p = 0; p < ib->proto_count; p++) {
        proto_entry *e = &ib->entries[p];
        void *blob;
        brt_result r = brt_stream_bvh(brt_run_prototype_stream, source, p, &ib->protos[p], &e->triangles,
                                  NULL, NULL, err);
        if (r == BRT_OK) r = poll_interrupt(b, err);
        if (r != BRT_OK) return r;
        e->size = brt_bvh_blob_size(ib->protos[p]);
        if (!(blob = calloc(1, e->size ? e->size : 1)))
            return brt_fail(err, BRT_ENOMEM, "%s: out of memory", b->w.path);
        brt_bvh_blob_write(ib->protos[p], blob);
        e->checksum = brt_checksum64(blob, e->size);
        e->offset = b->w.offset;
        brt_bvh_bounds(ib->protos[p], e->lo, e->hi);
        r = write_at(b->w.fd, blob, e->size, e->offset, b->w.path, err);
        free(blob);
        if (r != BRT_OK) return r;
        b->w.offset = brt_round_up_page(e->offset + e->size);
        b->w.geometry_bytes += e->size;
    }
    return BRT_OK;
}

/* The margin of some slots about the centre of lo..hi (their frames are
** made again: they passed brt_instance_frame_init in pass A). */
static void slots_margin(const instance_build *ib, const uint32_t *slots, uint32_t n,
                         const float lo[3], const float hi[3], instance_margin *m)
{
    uint32_t i;
    brt_margin_begin(m, lo, hi);
    for (i = 0; i < n; i++) {
        const uint32_t k = slots ? slots[i] : i;
        brt_instance_frame f;
        if (brt_instance_frame_init(&ib->items[k], 0, &f, NULL) == BRT_OK) brt_margin_add(m, &f, ib->radii[k]);
    }
}

/* The proxy of a point of instances: each instance voxelized through its
** prototype's BVH (w->instance_voxels), dilated by INSTANCE_DILATION of a
** voxel.  The grid covers the point's box grown by a sixteenth of a voxel,
** more than the dilation, so that what the dilation marks beyond the box
** is inside. */
static brt_result instance_point_proxy(const instance_build *ib, const instance_point *ip,
                                       const float lo[3], const float hi[3], const scene_writer *w,
                                       brt_grid *grid)
{
    const uint32_t res = w->res;
    float glo[3], ghi[3], extent = 0.0f;
    uint32_t i;
    brt_result r;
    int a;
    for (a = 0; a < 3; a++)
        if (hi[a] - lo[a] > extent) extent = hi[a] - lo[a];
    for (a = 0; a < 3; a++) {
        glo[a] = lo[a] - extent / (16.0f * (float)res);
        ghi[a] = hi[a] + extent / (16.0f * (float)res);
    }
    r = brt_grid_init(grid, glo, ghi, res);
    for (i = 0; i < ip->n && r == BRT_OK; i++) {
        const brt_instance *in = &ib->items[ip->slots[i]];
        r = brt_voxelize_instance(grid, ib->protos[in->prototype], in->xform,
                                  INSTANCE_DILATION * grid->cell, w->instance_voxels);
    }
    return r;
}

/* The distinct prototypes of a point, ascending (a bitmap pass). */
static uint32_t *instance_point_uses(instance_build *ib, instance_point *ip)
{
    uint32_t *uses = malloc((size_t)ip->n * sizeof *uses), i, p;
    if (!uses) return NULL;
    ib->stamp_now++;
    for (i = 0; i < ip->n; i++) ib->stamp[ib->items[ip->slots[i]].prototype] = ib->stamp_now;
    ip->k = 0;
    ip->instanced = 0;
    for (p = 0; p < ib->proto_count; p++)
        if (ib->stamp[p] == ib->stamp_now) uses[ip->k++] = p;
    for (i = 0; i < ip->n; i++) ip->instanced += ib->entries[ib->items[ip->slots[i]].prototype].triangles;
    return uses;
}

/* Writes one point of instances: its table blob, entry, box and proxy. */
static brt_result instance_point_write(scene_builder *b, instance_build *ib, const uint32_t *slots,
                                       uint32_t n, brt_error *err)
{
    scene_writer *w = &b->w;
    instance_point ip;
    float *boxes = malloc(6 * (size_t)n * sizeof *boxes);
    uint32_t *uses = NULL, i, distinct;
    uint64_t instanced;
    top_node *nodes = NULL;
    unsigned char *blob = NULL;
    point_entry *e = NULL;
    brt_grid grid;
    brt_result r = poll_interrupt(b, err);
    grid.bits = NULL;
    ip.items = ib->items;
    ip.numbers = ib->numbers;
    ip.slots = slots;
    ip.n = n;
    for (i = 0; boxes && i < n; i++) memcpy(boxes + 6 * (size_t)i, ib->boxes + 6 * (size_t)slots[i], 6 * sizeof *boxes);
    if (r == BRT_OK && (!boxes || !(uses = instance_point_uses(ib, &ip)) ||
                        brt_top_build(boxes, n, &nodes, &ip.m) != BRT_OK ||
                        !(blob = malloc(instance_table_bytes(n, ip.m, ip.k))) || !(e = point_append(w))))
        r = brt_fail(err, BRT_ENOMEM, "%s: out of memory", w->path);
    if (r == BRT_OK) {
        ip.nodes = nodes;
        ip.uses = uses;
        instance_table_pack(&ip, blob);
        bounds_clear(e->lo, e->hi);
        for (i = 0; i < n; i++) {
            brt_bounds_grow(e->lo, e->hi, boxes + 6 * (size_t)i);
            brt_bounds_grow(e->lo, e->hi, boxes + 6 * (size_t)i + 3);
        }
        slots_margin(ib, slots, n, e->lo, e->hi, &e->margin);
        e->triangles = (uint32_t)instance_range_size(ib, slots, n, &distinct, &instanced);
        e->instances = n;
        e->instanced = ip.instanced;
        e->size = instance_table_bytes(n, ip.m, ip.k);
        e->checksum = brt_checksum64(blob, e->size);
        e->offset = w->offset;
        r = write_at(w->fd, blob, e->size, e->offset, w->path, err);
    }
    if (r == BRT_OK) {
        w->offset = brt_round_up_page(e->offset + e->size);
        w->geometry_bytes += e->size;
        memcpy(w->boxes + 6 * (size_t)(w->point_count - 1), e->lo, 3 * sizeof(float));
        memcpy(w->boxes + 6 * (size_t)(w->point_count - 1) + 3, e->hi, 3 * sizeof(float));
        r = instance_point_proxy(ib, &ip, e->lo, e->hi, w, &grid);
        if (r == BRT_OK) r = brt_svdag_add(w->dag, &grid, &e->proxy);
        e->inner.root = BRT_EMPTY_ROOT;   /* no inner proxies for instances */
        if (r != BRT_OK) r = brt_fail(err, r, "%s: building a proxy: %s", w->path, brt_result_string(r));
    }
    brt_grid_free(&grid);
    free(boxes);
    free(uses);
    free(nodes);
    free(blob);
    return r;
}

/* scene_builder.leaf of the instance pass: a bucket of instances read
** back, partitioned by brt_partition_by_size, each part written as a point. */
static brt_result instance_bucket(scene_builder *b, const bucket *bk, brt_error *err)
{
    instance_build *ib = b->ib;
    partition parts;
    size_limits limits;
    uint32_t i;
    brt_result r = instance_bucket_read(b, ib, bk, err);
    memset(&parts, 0, sizeof parts);
    if (r != BRT_OK) return r;
    limits.point_tris = b->point_tris;
    limits.point_instanced = b->point_instanced;
    if (!(parts.order = malloc((size_t)ib->count * sizeof *parts.order)))
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", b->w.path);
    for (i = 0; i < ib->count; i++) parts.order[i] = i;
    r = brt_partition_by_size(&parts, ib->centres, 0, ib->count, &limits, instance_range_size, ib);
    if (r != BRT_OK) r = brt_fail(err, r, "%s: out of memory", b->w.path);
    for (i = 0; i < parts.count && r == BRT_OK; i++)
        r = instance_point_write(b, ib, parts.order + parts.ranges[i].first, parts.ranges[i].count, err);
    free(parts.order);
    free(parts.ranges);
    return r;
}

/* The arrays of one bucket of instances, and the instance file beside the
** scene (unlinked at once, like the spill file). */
static brt_result instance_pass_init(scene_builder *b, instance_build *ib, brt_error *err)
{
    char path[4096];
    const uint32_t cap = b->instance_bucket;
    int a;
    ib->cap = cap;
    ib->items = malloc((size_t)cap * sizeof *ib->items);
    ib->numbers = malloc((size_t)cap * sizeof *ib->numbers);
    ib->boxes = malloc(6 * (size_t)cap * sizeof *ib->boxes);
    ib->centres = malloc(3 * (size_t)cap * sizeof *ib->centres);
    ib->radii = malloc((size_t)cap * sizeof *ib->radii);
    ib->recs = malloc((size_t)cap * sizeof *ib->recs);
    if (!ib->items || !ib->numbers || !ib->boxes || !ib->centres || !ib->radii || !ib->recs)
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", b->w.path);
    for (a = 0; a < 3; a++) {
        ib->dlo[a] = INFINITY;
        ib->dhi[a] = -INFINITY;
    }
    if (snprintf(path, sizeof path, "%s.instances.%ld", b->w.path, (long)getpid()) >= (int)sizeof path)
        return brt_fail(err, BRT_EARG, "%s: path too long", b->w.path);
    b->instance_fd = open(path, O_RDWR | O_CREAT | O_TRUNC, 0600);
    if (b->instance_fd < 0)
        return brt_fail(err, BRT_EIO, "%s: cannot create: %s", b->w.path, strerror(errno));
    unlink(path);
    return BRT_OK;
}

/* Pass A of the instances, then their buckets (see above). */
static brt_result build_instance_points(scene_builder *b, const brt_scene_source *source,
                                        instance_build *ib, brt_error *err)
{
    brt_result r = instance_pass_init(b, ib, err);
    if (r != BRT_OK || !source->instances) return r;
    b->ib = ib;
    ib->root.b.first = b->spill_end;
    ib->root.buf = b->read_buf;
    ib->root.cap = b->chunk;
    bounds_clear(ib->root.b.lo, ib->root.b.hi);
    r = source->instances(source->user, spill_instances, b, err);
    if (r == BRT_OK) r = spill_flush(b, &ib->root, err);
    if (r != BRT_OK || ib->root.b.count == 0) return r;
    b->spill_end += ib->root.b.count;
    b->leaf = instance_bucket;
    b->bucket_tris = ib->cap;
    return process_bucket(b, &ib->root.b, err);
}

static void instance_build_free(instance_build *ib)
{
    uint32_t p;
    for (p = 0; ib->protos && p < ib->proto_count; p++) brt_bvh_free(ib->protos[p]);
    free(ib->protos);
    free(ib->entries);
    free(ib->stamp);
    free(ib->items);
    free(ib->numbers);
    free(ib->boxes);
    free(ib->centres);
    free(ib->radii);
    free(ib->recs);
}

/* ---- the file's tables ---- */

/* Writes a section at the next page and fills in its table entry. */
static brt_result write_section(scene_writer *w, const void *data, size_t size, section *s,
                                brt_error *err)
{
    s->offset = w->offset;
    s->size = size;
    s->checksum = brt_checksum64(data, size);
    w->offset = brt_round_up_page(w->offset + size);
    return write_at(w->fd, data, size, s->offset, w->path, err);
}

/* The point table, the top-level nodes and the DAG pool, (instanced:
** the prototype table,) then the header. */
static brt_result write_tables(scene_writer *w, scene_header *h, const proto_entry *protos,
                               brt_error *err)
{
    const size_t entry_bytes = header_instanced(h) ? POINT_ENTRY_BYTES_V4 : POINT_ENTRY_BYTES;
    const size_t proto_bytes = (size_t)h->prototype_count * PROTO_ENTRY_BYTES;
    size_t top_bytes, dag_bytes, table_bytes = (size_t)h->point_count * entry_bytes;
    top_node *nodes = NULL;
    unsigned char *buf, header[SCENE_HEADER_BYTES];
    uint32_t i;
    brt_result r = brt_top_build(w->boxes, h->point_count, &nodes, &h->top_node_count);
    if (r != BRT_OK) return brt_fail(err, r, "%s: out of memory", w->path);
    top_bytes = (size_t)h->top_node_count * TOP_NODE_BYTES;
    dag_bytes = brt_svdag_blob_size(w->dag);
    buf = malloc(table_bytes + top_bytes + dag_bytes + proto_bytes + 1);
    if (!buf) {
        free(nodes);
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", w->path);
    }
    for (i = 0; i < h->point_count; i++) {
        if (header_instanced(h)) batch_entry_pack_v4(&w->points[i], buf + (size_t)i * entry_bytes);
        else batch_entry_pack(&w->points[i], buf + (size_t)i * entry_bytes);
    }
    for (i = 0; i < h->prototype_count; i++)
        proto_entry_pack(&protos[i], buf + table_bytes + top_bytes + dag_bytes + (size_t)i * PROTO_ENTRY_BYTES);
    for (i = 0; i < h->top_node_count; i++) top_node_pack(&nodes[i], buf + table_bytes + (size_t)i * TOP_NODE_BYTES);
    brt_svdag_blob_write(w->dag, buf + table_bytes + top_bytes);
    free(nodes);
    r = write_section(w, buf, table_bytes, &h->sections[SECTION_POINTS], err);
    if (r == BRT_OK) r = write_section(w, buf + table_bytes, top_bytes, &h->sections[SECTION_TOP], err);
    if (r == BRT_OK) r = write_section(w, buf + table_bytes + top_bytes, dag_bytes, &h->sections[SECTION_DAG], err);
    if (r == BRT_OK && proto_bytes)
        r = write_section(w, buf + table_bytes + top_bytes + dag_bytes, proto_bytes,
                          &h->sections[SECTION_PROTOTYPES], err);
    free(buf);
    if (r != BRT_OK) return r;
    /* Pad to whole pages so the cache's page-rounded reads stay in the file. */
    if (ftruncate(w->fd, (off_t)w->offset) != 0)
        return brt_fail(err, BRT_EIO, "%s: cannot write: %s", w->path, strerror(errno));
    header_pack(h, header);
    return write_at(w->fd, header, sizeof header, 0, w->path, err);
}

/* ---- the build ---- */

/* The bucket arrays, sized for the largest bucket this stream can have. */
static brt_result builder_arrays(scene_builder *b, brt_error *err)
{
    size_t most = b->root.b.count < b->bucket_tris ? b->root.b.count : b->bucket_tris, i;
    size_t point = most < b->point_tris ? most : b->point_tris;
    uint32_t k;
    b->records = malloc(most * sizeof *b->records);
    b->centroids = malloc(3 * most * sizeof *b->centroids);
    b->order = malloc(most * sizeof *b->order);
    b->indices = malloc(3 * point * sizeof *b->indices);
    b->window = 2 * b->pool.count;
    b->work = calloc(b->window, sizeof *b->work);
    if (!b->records || !b->centroids || !b->order || !b->indices || !b->work)
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", b->w.path);
    for (k = 0; k < b->window; k++) {
        b->work[k].corners = malloc(9 * point * sizeof *b->work[k].corners);
        b->work[k].prims = malloc(point * sizeof *b->work[k].prims);
        if (!b->work[k].corners || !b->work[k].prims)
            return brt_fail(err, BRT_ENOMEM, "%s: out of memory", b->w.path);
    }
    for (i = 0; i < 3 * point; i++) b->indices[i] = (uint32_t)i;
    return BRT_OK;
}

/* Pass A and the buckets: the batching points of the (world) triangles,
** none when the stream has none. */
static brt_result build_triangle_points(scene_builder *b, const brt_triangle_source *source,
                                        brt_error *err)
{
    brt_result r;
    b->root.cap = b->chunk;
    b->root.buf = b->read_buf;
    bounds_clear(b->root.b.lo, b->root.b.hi);
    r = source->run(source->user, spill_stream, b, err);
    if (r == BRT_OK) r = spill_flush(b, &b->root, err);
    if (r != BRT_OK || b->root.b.count == 0) return r;
    b->spill_end = b->root.b.count;
    if ((r = builder_arrays(b, err)) != BRT_OK) return r;
    return process_bucket(b, &b->root.b, err);
}

static brt_result builder_start(scene_builder *b, brt_error *err)
{
    brt_result r = brt_svdag_create(&b->w.dag);
    b->w.offset = SCENE_PAGE;
    return r == BRT_OK ? BRT_OK : brt_fail(err, r, "%s: out of memory", b->w.path);
}

/* Pass A, the buckets, the tables. */
static brt_result build_passes(scene_builder *b, const brt_triangle_source *source,
                               scene_header *h, brt_error *err)
{
    brt_result r = builder_start(b, err);
    if (r == BRT_OK) r = build_triangle_points(b, source, err);
    if (r != BRT_OK) return r;
    if (b->root.b.count == 0)
        return brt_fail(err, BRT_EARG, "%s: the mesh has no triangles", b->w.path);
    h->point_count = b->w.point_count;
    h->triangle_count = b->root.b.count;
    h->geometry_bytes = b->w.geometry_bytes;
    return write_tables(&b->w, h, NULL, err);
}

/* The walk's margin, about the centre of the scene: the largest condition
** number, and a reach from the bounds of the translations and the largest
** radius, which is no less than any instance's |d - centre| + radius
** (pass A kept these, not the instances). */
static void scene_margin(const scene_writer *w, const instance_build *ib, instance_margin *m)
{
    float lo[3], hi[3];
    double far = 0.0;
    uint32_t i;
    int a;
    bounds_clear(lo, hi);
    for (i = 0; i < w->point_count; i++) {
        brt_bounds_grow(lo, hi, w->boxes + 6 * (size_t)i);
        brt_bounds_grow(lo, hi, w->boxes + 6 * (size_t)i + 3);
    }
    brt_margin_begin(m, lo, hi);
    if (ib->slots == 0) return;
    for (a = 0; a < 3; a++) {
        far = fmax(far, fabs(ib->dlo[a] - m->center[a]));
        far = fmax(far, fabs(ib->dhi[a] - m->center[a]));
    }
    m->condition = ib->condition;
    m->reach = nextafterf((float)((far + ib->radius) * (1.0 + 0x1p-20)), INFINITY);
}

/* An instanced scene: the world triangles' points, the prototypes, the
** points of instances, the tables. */
static brt_result build_instanced_passes(scene_builder *b, const brt_scene_source *source,
                                         scene_header *h, brt_error *err)
{
    instance_build ib;
    brt_result r;
    memset(&ib, 0, sizeof ib);
    ib.proto_count = source->prototype_count;
    ib.protos = calloc(ib.proto_count, sizeof *ib.protos);
    ib.entries = calloc(ib.proto_count, sizeof *ib.entries);
    ib.stamp = calloc(ib.proto_count, sizeof *ib.stamp);
    r = ib.protos && ib.entries && ib.stamp ? builder_start(b, err)
                                            : brt_fail(err, BRT_ENOMEM, "%s: out of memory", b->w.path);
    if (r == BRT_OK && source->world.run) r = build_triangle_points(b, &source->world, err);
    if (r == BRT_OK) r = build_prototypes(b, source, &ib, err);
    if (r == BRT_OK) r = build_instance_points(b, source, &ib, err);
    if (r == BRT_OK && b->w.point_count == 0)
        r = brt_fail(err, BRT_EARG, "%s: the scene has no triangles", b->w.path);
    if (r == BRT_OK) {
        h->point_count = b->w.point_count;
        h->triangle_count = b->root.b.count;
        h->geometry_bytes = b->w.geometry_bytes;
        h->prototype_count = ib.proto_count;
        h->instance_count = ib.streamed;
        h->instanced_triangles = ib.instanced + b->root.b.count;
        scene_margin(&b->w, &ib, &h->margin);
        r = write_tables(&b->w, h, ib.entries, err);
    }
    instance_build_free(&ib);
    return r;
}

static void builder_free(scene_builder *b)
{
    uint32_t k;
    if (b->spill_fd >= 0) close(b->spill_fd);
    if (b->instance_fd >= 0) close(b->instance_fd);
    free(b->read_buf);
    free(b->cells);
    free(b->records);
    free(b->centroids);
    free(b->order);
    free(b->points.ranges);
    free(b->indices);
    for (k = 0; b->work && k < b->window; k++) {
        free(b->work[k].corners);
        free(b->work[k].prims);
    }
    free(b->work);
    brt_pool_free(&b->pool);
    brt_svdag_free(b->w.dag);
    free(b->w.points);
    free(b->w.boxes);
}

#ifdef BRT_TESTING
/* The tests' sizes of a build (testing.h: brt_test_build_sizes); 0: the
** defaults. */
static uint32_t test_spill_chunk, test_bucket_tris;

void brt_test_build_sizes(uint32_t spill_chunk, uint32_t bucket_tris)
{
    test_spill_chunk = spill_chunk;
    test_bucket_tris = bucket_tris;
}
#else
enum { test_spill_chunk = 0, test_bucket_tris = 0 };   /* the defaults */
#endif

static brt_result builder_init(scene_builder *b, const brt_scene_options *opt,
                               const char *scene_path, brt_error *err)
{
    uint32_t cap = test_bucket_tris ? test_bucket_tris
                                    : (uint32_t)(BUCKET_BYTES / sizeof(spill_record));
    char spill_path[4096];
    memset(b, 0, sizeof *b);
    b->spill_fd = b->w.fd = b->instance_fd = -1;
    b->leaf = build_bucket;
    b->w.path = scene_path;
    b->interrupt = opt ? opt->interrupt : NULL;
    b->point_instanced = opt ? opt->point_instanced : 0;
    brt_pool_init(&b->pool, opt ? opt->threads : 0);
    scene_options_resolve(opt, &b->point_tris, &b->w.res);
    b->w.instance_voxels = scene_options_instance_voxels(opt);
    if (!brt_proxy_res_valid(b->w.res))
        return brt_fail(err, BRT_EARG, "proxy resolution %u is not a power of two in 2..1024", b->w.res);
    /* A bucket of instances holds about four times the bytes of a spill
    ** record per instance, so it holds a quarter as many. */
    b->instance_bucket = cap / 4 > 0 ? cap / 4 : 1;
    b->bucket_tris = cap / b->point_tris * b->point_tris;
    if (b->bucket_tris < b->point_tris) b->bucket_tris = b->point_tris;
    b->chunk = test_spill_chunk ? test_spill_chunk : SPILL_CHUNK;
    if (brt_is_special_file(scene_path))
        return brt_fail(err, BRT_EARG, "%s: not a regular file", scene_path);
    if (snprintf(spill_path, sizeof spill_path, "%s.spill.%ld", scene_path,
                 (long)getpid()) >= (int)sizeof spill_path)
        return brt_fail(err, BRT_EARG, "%s: path too long", scene_path);
    if (!(b->read_buf = malloc((size_t)b->chunk * sizeof *b->read_buf)))
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", scene_path);
    /* Unlinked at once: the descriptor keeps it, and nothing can leave it
    ** behind.  (Messages name the scene, as for the scene's own file.) */
    b->spill_fd = open(spill_path, O_RDWR | O_CREAT | O_TRUNC, 0600);
    if (b->spill_fd < 0)
        return brt_fail(err, BRT_EIO, "%s: cannot create: %s", scene_path, strerror(errno));
    unlink(spill_path);
    return BRT_OK;
}

/* Either build: a triangle stream (instanced NULL) or an instanced scene. */
static brt_result build_scene_file(const brt_triangle_source *source,
                                   const brt_scene_source *instanced,
                                   const brt_scene_options *opt, uint64_t source_stamp,
                                   const char *scene_path, brt_error *err)
{
    scene_builder b;
    scene_header h;
    brt_atomic_file file;
    brt_result r;
    memset(&h, 0, sizeof h);
    file.tmp[0] = 0;
    r = builder_init(&b, opt, scene_path, err);
    if (r == BRT_OK) r = brt_atomic_open(&file, scene_path, err);
    if (r == BRT_OK) b.w.fd = file.fd;
    h.point_tris = b.point_tris;
    h.proxy_res = b.w.res;
    h.stamp = source_stamp;
    h.point_instanced = instanced ? b.point_instanced : 0;
    h.instance_voxels = instanced ? (uint32_t)b.w.instance_voxels : 0;
    if (r == BRT_OK)
        r = instanced ? build_instanced_passes(&b, instanced, &h, err) : build_passes(&b, source, &h, err);
    r = brt_atomic_close(&file, r, err);
    builder_free(&b);
    return r;
}

brt_result brt_scene_build_stream(const brt_triangle_source *source,
                                  const brt_scene_options *opt, uint64_t source_stamp,
                                  const char *scene_path, brt_error *err)
{
    return build_scene_file(source, NULL, opt, source_stamp, scene_path, err);
}

brt_result brt_scene_build_source(const brt_scene_source *source, const brt_scene_options *opt,
                                  uint64_t source_stamp, const char *scene_path, brt_error *err)
{
    if (source->prototype_count == 0) {
        if (!source->world.run)
            return brt_fail(err, BRT_EARG, "%s: the scene has no triangles", scene_path);
        return build_scene_file(&source->world, NULL, opt, source_stamp, scene_path, err);
    }
    return build_scene_file(NULL, source, opt, source_stamp, scene_path, err);
}

brt_result brt_scene_build(const brt_mesh *mesh, const brt_scene_options *opt,
                           uint64_t source_stamp, const char *scene_path,
                           brt_error *err)
{
    brt_triangle_source source;
    brt_mesh_memory_source(mesh, &source);
    return brt_scene_build_stream(&source, opt, source_stamp, scene_path, err);
}

brt_result brt_scene_source_stamp(const char *mesh_path, uint64_t *stamp, brt_error *err)
{
    struct stat st;
    uint64_t parts[4];
    if (stat(mesh_path, &st) != 0)
        return brt_fail(err, BRT_EIO, "%s: %s", mesh_path, strerror(errno));
    /* Size, modification time to the nanosecond (POSIX.1-2008) and inode,
    ** hashed into one number: what make trusts, plus a replaced file. */
    parts[0] = (uint64_t)st.st_size;
    parts[1] = (uint64_t)st.st_mtim.tv_sec;
    parts[2] = (uint64_t)st.st_mtim.tv_nsec;
    parts[3] = (uint64_t)st.st_ino;
    *stamp = brt_checksum64(parts, sizeof parts);
    return BRT_OK;
}

/* ---- opening a scene file ------------------------------------------- */

/* pread until done, through the given reader: short reads and EINTR are
** retried; an error or an early end of file is reported, never ignored. */
brt_result brt_read_fully(int fd, void *buf, size_t size, uint64_t offset,
                             brt_read_fn read_fn, void *user, uint64_t *bytes_read,
                             const char *path, brt_error *err)
{
    unsigned char *p = buf;
    while (size > 0) {
        long n;
        errno = 0;
        n = read_fn(fd, p, size, offset, user);
        if (n < 0 && errno == EINTR) continue;
        if (n < 0)
            return brt_fail(err, BRT_EIO, "%s: read at byte %llu failed: %s", path,
                            (unsigned long long)offset, strerror(errno ? errno : EIO));
        if (n == 0)
            return brt_fail(err, BRT_EFORMAT, "%s: truncated (end of file at byte %llu)",
                            path, (unsigned long long)offset);
        if ((size_t)n > size) n = (long)size;
        p += n;
        size -= (size_t)n;
        offset += (uint64_t)n;
        if (bytes_read) *bytes_read += (uint64_t)n;
    }
    return BRT_OK;
}

#ifdef BRT_TESTING
/* The tests' injected read fault (testing.h: brt_test_read_fault): reads
** left before it, or -1 (never). */
static long read_fault_after = -1;
static int read_fault_errno;

void brt_test_read_fault(long after, int error)
{
    read_fault_after = after;
    read_fault_errno = error;
}
#endif

/* Every read of the library's own (a scene file's header, tables and
** blobs, the spill file) when the caller gives no brt_read_fn. */
long brt_pread_reader(int fd, void *buf, size_t size, uint64_t offset, void *user)
{
    (void)user;
#ifdef BRT_TESTING
    if (read_fault_after >= 0 && read_fault_after-- == 0) {
        errno = read_fault_errno;
        return -1;
    }
#endif
    return (long)pread(fd, buf, size, (off_t)offset);
}

/* Reads a section into a fresh buffer and checks its checksum. */
static brt_result read_section(brt_scene *s, int which, const char *what, void **out,
                               brt_error *err)
{
    const section *sec = &s->header.sections[which];
    void *buf;
    brt_result r;
    *out = NULL;
    if (sec->offset > s->file_size || sec->size > s->file_size - sec->offset)
        return brt_fail(err, BRT_EFORMAT, "%s: %s lies outside the file (truncated?)", s->path, what);
    buf = malloc(sec->size ? sec->size : 1);
    if (!buf) return brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    r = brt_read_fully(s->fd, buf, sec->size, sec->offset, brt_pread_reader, NULL, NULL, s->path, err);
    if (r == BRT_OK && brt_checksum64(buf, sec->size) != sec->checksum)
        r = brt_fail(err, BRT_EFORMAT, "%s: %s checksum mismatch (corrupt file)", s->path, what);
    if (r != BRT_OK) {
        free(buf);
        return r;
    }
    *out = buf;
    return BRT_OK;
}

/* ---- validating a scene file at open ---------------------------------- */
/*
** A checksum tells a damaged file from the one that was written, not a
** forged or miswritten one: a file whose checksums match may still say
** anything.  So opening a scene validates every cross-reference once,
** before anything is traced, one validator per structure:
**   check_header   counts and section sizes agree with one another
**   (read_section) each section lies inside the file and matches its sum
**   brt_svdag_blob_open (svdag.c): the DAG pool, its child indices
**   check_batch    one table entry: box, blob extent, proxy (proxy_valid)
**   check_points  the table against the header: triangles and bytes add up
**   check_top      the top level: a tree over every batching point, boxes
**                  ordered, finite and nested
** and every blob load (blob_read) runs brt_bvh_blob_open (bvh.c: indices,
** boxes, finite triangles, triangle numbers below the scene's count) and
** check_blob (its triangle count is its table entry's).  The walk, the
** proxy cast and the BVH traversal then trust what they read: no test on
** the hot path.  A failure is BRT_EFORMAT, "FILE: PART: what is wrong".
*/

/* Finite and ordered: what the box tests of the walk rely on. */
static int box_valid(const float lo[3], const float hi[3])
{
    int a;
    for (a = 0; a < 3; a++)
        if (!isfinite(lo[a]) || !isfinite(hi[a]) || !(lo[a] <= hi[a])) return 0;
    return 1;
}

/* A margin a file may hold: finite, condition within the bound. */
static int margin_valid(const instance_margin *m)
{
    return m->condition >= 0 && m->condition <= nextafterf((float)BRT_MAX_CONDITION, INFINITY) &&
           m->reach >= 0 && m->reach <= FLT_MAX && isfinite(m->center[0]) &&
           isfinite(m->center[1]) && isfinite(m->center[2]);
}

/* The counts of the header against one another and the section sizes. */
static brt_result check_header(const brt_scene *s, brt_error *err)
{
    const scene_header *h = &s->header;
    if (h->point_count == 0)
        return brt_fail(err, BRT_EFORMAT, "%s: header: no batching points", s->path);
    if (h->top_node_count == 0 || h->top_node_count > h->point_count)
        return brt_fail(err, BRT_EFORMAT, "%s: header: %u top-level nodes for %u batching points",
                        s->path, h->top_node_count, h->point_count);
    if (h->sections[SECTION_POINTS].size !=
        (uint64_t)h->point_count * (header_instanced(h) ? POINT_ENTRY_BYTES_V4 : POINT_ENTRY_BYTES))
        return brt_fail(err, BRT_EFORMAT, "%s: header: point table has the wrong size", s->path);
    if (h->sections[SECTION_PROTOTYPES].size != (uint64_t)h->prototype_count * PROTO_ENTRY_BYTES)
        return brt_fail(err, BRT_EFORMAT, "%s: header: prototype table has the wrong size", s->path);
    if (header_instanced(h) && !margin_valid(&h->margin))
        return brt_fail(err, BRT_EFORMAT, "%s: header: margin out of range", s->path);
    if (h->sections[SECTION_TOP].size != (uint64_t)h->top_node_count * TOP_NODE_BYTES)
        return brt_fail(err, BRT_EFORMAT, "%s: header: top-level section has the wrong size", s->path);
    return BRT_OK;
}

/* The header's resolution, and all that brt_proxy_raycast relies on:
** brt_proxy_check (res a power of two, origin and cell finite, cell
** positive, root a node of the pool at the depth res needs), so the cast
** need not check again.
** (The far corner origin + res * cell may overflow a float, at coordinates
** near FLT_MAX, but the cast maps rays into the grid's frame in double.) */
static int proxy_valid(const brt_scene *s, const brt_proxy *p)
{
    return p->res == s->header.proxy_res && brt_proxy_check(s->dag, p, NULL) == BRT_OK;
}

/* An inner proxy: a root of the pool at the resolution inner_res gives. */
static int inner_valid(const brt_scene *s, const brt_proxy *p)
{
    return p->res == inner_res(s->header.proxy_res) && brt_proxy_check(s->dag, p, NULL) == BRT_OK;
}

/* A blob lies inside the file, in whole pages (as the cache reads it). */
static int blob_inside(const brt_scene *s, uint64_t offset, uint64_t size)
{
    return offset % SCENE_PAGE == 0 && size <= s->file_size &&
           offset <= s->file_size - brt_round_up_page(size);
}

/* One point table entry: its box, its blob inside the file (whole pages,
** as the cache reads them), its proxy. */
static brt_result check_batch(const brt_scene *s, uint32_t i, const point_entry *b, brt_error *err)
{
    if (!box_valid(b->lo, b->hi))
        return brt_fail(err, BRT_EFORMAT, "%s: batching point %u: box not finite or inverted",
                        s->path, i);
    if (!blob_inside(s, b->offset, b->size))
        return brt_fail(err, BRT_EFORMAT, "%s: batching point %u: blob outside the file", s->path, i);
    if (b->instances && (!header_instanced(&s->header) || b->instances > s->header.instance_count ||
                         !margin_valid(&b->margin)))
        return brt_fail(err, BRT_EFORMAT, "%s: batching point %u: %u instances or margin out of range",
                        s->path, i, b->instances);
    if (!proxy_valid(s, &b->proxy))
        return brt_fail(err, BRT_EFORMAT, "%s: batching point %u: invalid proxy", s->path, i);
    if (!inner_valid(s, &b->inner))
        return brt_fail(err, BRT_EFORMAT, "%s: batching point %u: invalid inner proxy", s->path, i);
    return BRT_OK;
}

/* The table against the header: the entries' triangles and blob bytes
** add up to the header's counts. */
static brt_result check_points(const brt_scene *s, brt_error *err)
{
    uint64_t triangles = 0, bytes = 0;
    uint32_t i;
    for (i = 0; i < s->header.point_count; i++) {
        brt_result r = check_batch(s, i, &s->points[i], err);
        if (r != BRT_OK) return r;
        if (!s->points[i].instances) triangles += s->points[i].triangles;
        bytes += s->points[i].size;
    }
    for (i = 0; i < s->header.prototype_count; i++) bytes += s->prototypes[i].size;
    if (triangles != s->header.triangle_count)
        return brt_fail(err, BRT_EFORMAT, "%s: point table: batching points hold %llu triangles, "
                        "header says %u", s->path, (unsigned long long)triangles,
                        s->header.triangle_count);
    if (bytes != s->header.geometry_bytes)
        return brt_fail(err, BRT_EFORMAT, "%s: point table: blobs hold %llu bytes, header says %llu",
                        s->path, (unsigned long long)bytes,
                        (unsigned long long)s->header.geometry_bytes);
    return BRT_OK;
}

/* The frame of a batching point's inner proxy, as the build made it: the
** grid brt_grid_init fits to its box at inner_res (res 0, which no check
** passes, when the box is not valid: check_batch names that first).
** brt_grid_init allocates the grid's bits too, so it can run out of
** memory: that is reported as such, not as an invalid inner proxy. */
static brt_result inner_frame(point_entry *b, uint32_t proxy_res)
{
    brt_grid g;
    brt_result r = box_valid(b->lo, b->hi) ? brt_grid_init(&g, b->lo, b->hi, inner_res(proxy_res)) : BRT_EARG;
    b->inner.res = 0;
    if (r != BRT_OK) return r == BRT_ENOMEM ? r : BRT_OK;
    b->inner.res = g.res;
    memcpy(b->inner.origin, g.origin, sizeof g.origin);
    b->inner.cell = g.cell;
    brt_grid_free(&g);
    return BRT_OK;
}

static brt_result load_points(brt_scene *s, brt_error *err)
{
    unsigned char *table;
    uint32_t i;
    brt_result r = read_section(s, SECTION_POINTS, "point table", (void **)&table, err);
    if (r != BRT_OK) return r;
    s->points = malloc(((size_t)s->header.point_count + 1) * sizeof *s->points);
    if (!s->points) {
        free(table);
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    }
    for (i = 0; i < s->header.point_count; i++) {
        const size_t bytes = header_instanced(&s->header) ? POINT_ENTRY_BYTES_V4 : POINT_ENTRY_BYTES;
        const unsigned char *p = table + (size_t)i * bytes;
        batch_entry_unpack(p, &s->points[i]);
        if (header_instanced(&s->header)) {
            point_entry *e = &s->points[i];
            e->instances = brt_get_le32(p + 80);
            e->instanced = brt_get_le64(p + 88);
            brt_margin_begin(&e->margin, e->lo, e->hi);
            e->margin.condition = get_f32(p + 84);
            e->margin.reach = get_f32(p + 96);
        }
        if (inner_frame(&s->points[i], s->header.proxy_res) != BRT_OK) {
            free(table);
            return brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
        }
    }
    free(table);
    return check_points(s, err);
}

/* Lane `lane` of node n holds the box lo, hi (inclusive: the build's lane
** box is the union of what it holds, so it may equal it). */
static int lane_holds(const top_node *n, int lane, const float lo[3], const float hi[3])
{
    int a;
    for (a = 0; a < 3; a++)
        if (!(n->box[a][lane] <= lo[a] && hi[a] <= n->box[3 + a][lane])) return 0;
    return 1;
}

/* Lane `lane` of node n holds every box of child node c and c's boxes
** are valid (they are checked as a lane of c in turn). */
static int lane_holds_node(const top_node *n, int lane, const top_node *c)
{
    int k, a;
    for (k = 0; k < 4; k++) {
        float lo[3], hi[3];
        if (c->child[k] == TOP_EMPTY) continue;
        for (a = 0; a < 3; a++) {
            lo[a] = c->box[a][k];
            hi[a] = c->box[3 + a][k];
        }
        if (!lane_holds(n, lane, lo, hi)) return 0;
    }
    return 1;
}

/* One lane in use of node i: the child's index in range, the lane's box
** finite, ordered and around what the child holds. */
static brt_result check_top_lane(const brt_scene *s, uint32_t i, int lane,
                                 unsigned char *has_parent, unsigned char *seen, brt_error *err)
{
    const top_node *n = &s->top[i];
    uint32_t c = n->child[lane];
    float lo[3], hi[3];
    int a;
    for (a = 0; a < 3; a++) {
        lo[a] = n->box[a][lane];
        hi[a] = n->box[3 + a][lane];
    }
    if (c & TOP_LEAF) {
        c &= ~TOP_LEAF;
        if (c >= s->header.point_count || seen[c]++)
            return brt_fail(err, BRT_EFORMAT, "%s: top-level node %u: bad leaf", s->path, i);
        if (!lane_holds(n, lane, s->points[c].lo, s->points[c].hi))
            return brt_fail(err, BRT_EFORMAT, "%s: top-level node %u: box does not hold batching "
                            "point %u", s->path, i, c);
    } else if (c <= i || c >= s->header.top_node_count || has_parent[c]++) {
        return brt_fail(err, BRT_EFORMAT, "%s: top-level node %u: bad child", s->path, i);
    } else if (!lane_holds_node(n, lane, &s->top[c])) {
        return brt_fail(err, BRT_EFORMAT, "%s: top-level node %u: box does not hold node %u",
                        s->path, i, c);
    }
    if (!box_valid(lo, hi))
        return brt_fail(err, BRT_EFORMAT, "%s: top-level node %u: box not finite or inverted",
                        s->path, i);
    return BRT_OK;
}

/* Every child index points forward, every node but the root has one
** parent and every batching point is a leaf exactly once: the nodes form
** a tree, so a walk terminates, never indexes out of range and meets each
** node and point at most once (the size of its heap).  Every box holds
** what is below it, so a subtree is entered no later than anything in it
** (the walk's skip rule (a) relies on that).  Runs on the file's exact
** boxes, before brt_top_node_pad. */
static brt_result check_top(brt_scene *s, brt_error *err)
{
    uint32_t n = s->header.top_node_count, count = s->header.point_count, i;
    unsigned char *has_parent = calloc((size_t)n + 1, 1), *seen = calloc((size_t)count + 1, 1);
    brt_result r = BRT_OK;
    int lane;
    if (!has_parent || !seen) r = brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    for (i = 0; i < n && r == BRT_OK; i++)
        for (lane = 0; lane < 4 && r == BRT_OK; lane++)
            if (s->top[i].child[lane] != TOP_EMPTY)
                r = check_top_lane(s, i, lane, has_parent, seen, err);
    for (i = 0; i < count && r == BRT_OK; i++)
        if (!seen[i]) r = brt_fail(err, BRT_EFORMAT, "%s: batching point %u not in the top level", s->path, i);
    free(has_parent);
    free(seen);
    return r;
}

static brt_result load_top(brt_scene *s, brt_error *err)
{
    unsigned char *raw;
    uint32_t i;
    brt_result r = read_section(s, SECTION_TOP, "top-level BVH", (void **)&raw, err);
    if (r != BRT_OK) return r;
    s->top = malloc(((size_t)s->header.top_node_count + 1) * sizeof *s->top);
    if (!s->top) {
        free(raw);
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    }
    for (i = 0; i < s->header.top_node_count; i++)
        top_node_unpack(raw + (size_t)i * TOP_NODE_BYTES, &s->top[i]);
    free(raw);
    r = check_top(s, err);
    for (i = 0; r == BRT_OK && i < s->header.top_node_count; i++) brt_top_node_pad(&s->top[i]);
    return r;
}

/* The prototype table (instanced files): each blob inside the file, each
** box valid (or empty, for a prototype without triangles). */
static brt_result load_prototypes(brt_scene *s, brt_error *err)
{
    unsigned char *table = NULL;
    uint32_t i, n = s->header.prototype_count;
    brt_result r = n ? read_section(s, SECTION_PROTOTYPES, "prototype table", (void **)&table, err)
                     : BRT_OK;
    if (r != BRT_OK) return r;
    s->prototypes = malloc(((size_t)n + 1) * sizeof *s->prototypes);
    if (!s->prototypes) r = brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    for (i = 0; i < n && r == BRT_OK; i++) {
        proto_entry *e = &s->prototypes[i];
        proto_entry_unpack(table + (size_t)i * PROTO_ENTRY_BYTES, e);
        if (!blob_inside(s, e->offset, e->size))
            r = brt_fail(err, BRT_EFORMAT, "%s: prototype %u: blob outside the file", s->path, i);
        else if (e->triangles ? !box_valid(e->lo, e->hi) : e->lo[0] <= e->hi[0])
            r = brt_fail(err, BRT_EFORMAT, "%s: prototype %u: box not finite or inverted", s->path, i);
    }
    free(table);
    return r;
}

static int blob_offset_order(const void *a, const void *b)
{
    const uint64_t x = ((const blob_place *)a)->offset, y = ((const blob_place *)b)->offset;
    return (x > y) - (x < y);
}

/* No two blobs share a page, and none the header's: each table entry is
** checked alone (check_batch), so a forged table could point two
** batching points at one blob holding as many triangles as both say, and
** a trace would answer with the wrong triangles (tests/test_hardening.c,
** blob_overlap). */
static brt_result check_blobs_apart(const brt_scene *s, brt_error *err)
{
    const uint32_t n = s->header.point_count + s->header.prototype_count;
    blob_place *sorted = malloc((size_t)n * sizeof *sorted);
    uint64_t free_from = SCENE_PAGE;
    uint32_t i;
    if (!sorted) return brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    memcpy(sorted, s->blobs, (size_t)n * sizeof *sorted);
    qsort(sorted, n, sizeof *sorted, blob_offset_order);
    for (i = 0; i < n && sorted[i].offset >= free_from; i++)
        free_from = sorted[i].offset + brt_round_up_page(sorted[i].size);   /* blob_inside: no wrap */
    if (i < n) {
        const uint64_t at = sorted[i].offset;
        free(sorted);
        return brt_fail(err, BRT_EFORMAT, "%s: blob table: blobs overlap at byte %llu", s->path,
                        (unsigned long long)at);
    }
    free(sorted);
    return BRT_OK;
}

/* Where every blob lies: the batching points', then the prototypes'. */
static brt_result place_blobs(brt_scene *s, brt_error *err)
{
    const uint32_t b = s->header.point_count;
    uint32_t i;
    s->blobs = malloc(((size_t)b + s->header.prototype_count) * sizeof *s->blobs);
    if (!s->blobs) return brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    for (i = 0; i < b; i++) {
        s->blobs[i].offset = s->points[i].offset;
        s->blobs[i].size = s->points[i].size;
        s->blobs[i].checksum = s->points[i].checksum;
    }
    for (i = 0; i < s->header.prototype_count; i++) {
        s->blobs[b + i].offset = s->prototypes[i].offset;
        s->blobs[b + i].size = s->prototypes[i].size;
        s->blobs[b + i].checksum = s->prototypes[i].checksum;
    }
    return check_blobs_apart(s, err);
}

/* The pool copies the section (brt_svdag_blob_open), which goes at once:
** held beside the pool it would double the proxies' bytes that the
** budget charges once (make bench-island's render check saw it). */
static brt_result load_dag(brt_scene *s, brt_error *err)
{
    brt_error why;
    void *pool = NULL;
    brt_result r = read_section(s, SECTION_DAG, "proxy pool", &pool, err);
    if (r != BRT_OK) return r;
    r = brt_svdag_blob_open(pool, s->header.sections[SECTION_DAG].size, &s->dag, &why);
    free(pool);
    if (r != BRT_OK) return brt_fail(err, BRT_EFORMAT, "%s: proxy pool: %s", s->path, why.message);
    return BRT_OK;
}

brt_result brt_scene_open(const char *scene_path, brt_scene **out, brt_error *err)
{
    unsigned char header[SCENE_HEADER_BYTES];
    struct stat st;
    brt_scene *s = calloc(1, sizeof *s);
    brt_result r = BRT_OK;
    *out = NULL;
    if (!s || !(s->path = malloc(strlen(scene_path) + 1))) {
        free(s);
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", scene_path);
    }
    strcpy(s->path, scene_path);
    s->fd = open(scene_path, O_RDONLY);
    if (s->fd < 0 || fstat(s->fd, &st) != 0)
        r = brt_fail(err, BRT_EIO, "%s: cannot open: %s", scene_path, strerror(errno));
    else if ((s->file_size = (uint64_t)st.st_size) < SCENE_HEADER_BYTES)
        r = brt_fail(err, BRT_EFORMAT, "%s: truncated (%llu bytes, no header)", scene_path,
                     (unsigned long long)s->file_size);
    if (r == BRT_OK)
        r = brt_read_fully(s->fd, header, sizeof header, 0, brt_pread_reader, NULL, NULL, scene_path, err);
    if (r == BRT_OK) r = header_unpack(scene_path, header, &s->header, err);
    if (r == BRT_OK) r = check_header(s, err);
    if (r == BRT_OK) r = load_dag(s, err);
    if (r == BRT_OK) r = load_prototypes(s, err);
    if (r == BRT_OK) r = load_points(s, err);
    if (r == BRT_OK) r = load_top(s, err);
    if (r == BRT_OK) r = place_blobs(s, err);
    if (r != BRT_OK) {
        brt_scene_close(s);
        return r;
    }
    *out = s;
    return BRT_OK;
}

void brt_scene_close(brt_scene *s)
{
    if (!s) return;
    if (s->fd >= 0) close(s->fd);
    brt_svdag_free(s->dag);
    free(s->points);
    free(s->prototypes);
    free(s->blobs);
    free(s->top);
    free(s->path);
    free(s);
}

int brt_scene_matches(const brt_scene *s, uint64_t stamp, const brt_scene_options *opt)
{
    uint32_t point_tris, res;
    scene_options_resolve(opt, &point_tris, &res);
    return s->header.stamp == stamp && s->header.point_tris == point_tris &&
           s->header.proxy_res == res &&
           s->header.point_instanced == (opt && s->header.prototype_count ? opt->point_instanced : 0) &&
           s->header.instance_voxels ==
               (s->header.prototype_count ? (uint32_t)scene_options_instance_voxels(opt) : 0);
}

uint32_t brt_scene_point_count(const brt_scene *s) { return s->header.point_count; }
uint32_t brt_scene_prototype_count(const brt_scene *s) { return s->header.prototype_count; }

uint64_t brt_scene_unique_triangles(const brt_scene *s)
{
    uint64_t n = s->header.triangle_count;
    uint32_t p;
    for (p = 0; p < s->header.prototype_count; p++) n += s->prototypes[p].triangles;
    return n;
}

uint32_t brt_scene_instance_count(const brt_scene *s) { return s->header.instance_count; }

uint64_t brt_scene_instanced_triangles(const brt_scene *s)
{
    return s->header.prototype_count ? s->header.instanced_triangles : s->header.triangle_count;
}
uint32_t brt_scene_triangle_count(const brt_scene *s) { return s->header.triangle_count; }

void brt_scene_bounds(const brt_scene *s, float bmin[3], float bmax[3])
{
    uint32_t i;
    int a;
    for (a = 0; a < 3; a++) {
        bmin[a] = INFINITY;
        bmax[a] = -INFINITY;
    }
    for (i = 0; i < s->header.point_count; i++)
        for (a = 0; a < 3; a++) {
            if (s->points[i].lo[a] < bmin[a]) bmin[a] = s->points[i].lo[a];
            if (s->points[i].hi[a] > bmax[a]) bmax[a] = s->points[i].hi[a];
        }
}

brt_result brt_scene_prepare_source(const brt_scene_source *source, uint64_t source_stamp,
                                    const char *scene_path, const brt_scene_options *opt,
                                    brt_scene **out, int *rebuilt, brt_error *err)
{
    struct stat st;
    brt_result r;
    *out = NULL;
    if (rebuilt) *rebuilt = 0;
    if (stat(scene_path, &st) == 0) {
        r = brt_scene_open(scene_path, out, err);
        if (r != BRT_OK || brt_scene_matches(*out, source_stamp, opt)) return r;
        brt_scene_close(*out);   /* stale: the input or the settings changed */
        *out = NULL;
    }
    r = brt_scene_build_source(source, opt, source_stamp, scene_path, err);
    if (r != BRT_OK) return r;
    if (rebuilt) *rebuilt = 1;
    return brt_scene_open(scene_path, out, err);
}

brt_result brt_scene_prepare(const char *mesh_path, const char *scene_path,
                             const brt_scene_options *opt, brt_scene **out,
                             int *rebuilt, brt_error *err)
{
    uint64_t stamp;
    brt_scene_source source;
    brt_result r = brt_scene_source_stamp(mesh_path, &stamp, err);
    *out = NULL;
    if (rebuilt) *rebuilt = 0;
    if (r != BRT_OK) return r;
    memset(&source, 0, sizeof source);
    brt_mesh_file_source(mesh_path, &source.world);   /* never the whole mesh in memory */
    return brt_scene_prepare_source(&source, stamp, scene_path, opt, out, rebuilt, err);
}

/* ---- opening an instance table (a load of a point of instances) ---- */

static brt_result table_fail(const brt_scene *s, uint32_t id, brt_error *err, const char *what)
{
    return brt_fail(err, BRT_EFORMAT, "%s: batching point %u: instance table: %s", s->path, id, what);
}

/* The distinct prototypes: ascending, each a prototype of the scene. */
static brt_result table_uses(const brt_scene *s, uint32_t id, const unsigned char *p,
                             instance_set *set, brt_error *err)
{
    uint32_t i;
    for (i = 0; i < set->use_count; i++) {
        set->uses[i] = brt_get_le32(p + 4 * (size_t)i);
        if (set->uses[i] >= s->header.prototype_count || (i > 0 && set->uses[i] <= set->uses[i - 1]))
            return table_fail(s, id, err, "prototype list not ascending or out of range");
    }
    return BRT_OK;
}

static int uses_prototype(const instance_set *set, uint32_t proto)
{
    uint32_t lo = 0, hi = set->use_count;
    while (lo < hi) {
        const uint32_t mid = lo + (hi - lo) / 2;
        if (set->uses[mid] < proto) lo = mid + 1;
        else hi = mid;
    }
    return lo < set->use_count && set->uses[lo] == proto;
}

/* The records: numbers in range, prototypes among the listed ones, and
** transforms that brt_instance_frame_init accepts; their world boxes into
** boxes (6 floats each) and the margin's maxima into the set. */
static brt_result table_records(const brt_scene *s, uint32_t id, const unsigned char *p,
                                instance_set *set, float *boxes, brt_error *err)
{
    uint32_t i;
    int a;
    for (i = 0; i < set->count; i++, p += INSTANCE_RECORD_BYTES) {
        const proto_entry *pe;
        brt_instance in;
        brt_error why;
        float radius;
        set->ids[i] = brt_get_le32(p);
        set->prototypes[i] = in.prototype = brt_get_le32(p + 4);
        for (a = 0; a < 12; a++) in.xform[a] = get_f32(p + 8 + 4 * a);
        if (set->ids[i] >= s->header.instance_count || !uses_prototype(set, in.prototype))
            return table_fail(s, id, err, "instance number or prototype out of range");
        if (brt_instance_frame_init(&in, set->ids[i], &set->frames[i], &why) != BRT_OK)
            return brt_fail(err, BRT_EFORMAT, "%s: batching point %u: %s", s->path, id, why.message);
        pe = &s->prototypes[in.prototype];
        brt_instance_bounds(&in, &set->frames[i], pe->lo, pe->hi, boxes + 6 * (size_t)i,
                            boxes + 6 * (size_t)i + 3, &radius);
        brt_margin_add(&set->margin, &set->frames[i], radius);
    }
    /* The entry's margin gated the proxy before this load: it must cover
    ** the instances (a smaller one would have let rays through that the
    ** proxy's dilation does not cover). */
    if (set->margin.condition > s->points[id].margin.condition ||
        set->margin.reach > s->points[id].margin.reach)
        return table_fail(s, id, err, "margin smaller than its instances'");
    return BRT_OK;
}

/* The tree: children point forward (to nodes) or at records, every node
** but the root has one parent, every record is one leaf, depth at most
** SET_MAX_DEPTH (so SET_STACK holds a descent). */
static brt_result table_tree(const brt_scene *s, uint32_t id, const unsigned char *p,
                             instance_set *set, unsigned char *seen, unsigned char *depth,
                             brt_error *err)
{
    uint32_t i, c;
    int lane;
    for (i = 0; i < set->node_count; i++)
        for (lane = 0; lane < 4; lane++) set->nodes[i].child[lane] = brt_get_le32(p + 16 * (size_t)i + 4 * (size_t)lane);
    for (i = 0; i < set->node_count; i++)
        for (lane = 0; lane < 4; lane++) {
            c = set->nodes[i].child[lane];
            if (c == TOP_EMPTY) continue;
            if (c & TOP_LEAF) {
                if ((c & ~TOP_LEAF) >= set->count || seen[c & ~TOP_LEAF]++)
                    return table_fail(s, id, err, "tree leaf out of range or repeated");
            } else if (c <= i || c >= set->node_count || depth[c] || depth[i] >= SET_MAX_DEPTH) {
                return table_fail(s, id, err, "tree child out of range, shared or too deep");
            } else {
                depth[c] = (unsigned char)(depth[i] + 1);
            }
        }
    for (i = 0; i < set->count; i++)
        if (!seen[i]) return table_fail(s, id, err, "an instance outside the tree");
    for (i = 1; i < set->node_count; i++)
        if (!depth[i]) return table_fail(s, id, err, "a tree node without a parent");
    return BRT_OK;
}

/* The tree's boxes from the records' boxes, bottom up (children come
** after their parents), then grown for the box test. */
static void table_boxes(instance_set *set, const float *boxes)
{
    uint32_t i = set->node_count;
    while (i-- > 0) {
        top_node *n = &set->nodes[i];
        int lane, k, a;
        for (lane = 0; lane < 4; lane++) {
            const uint32_t c = n->child[lane];
            if (c == TOP_EMPTY) continue;
            brt_top_lane_clear(n, lane);
            n->child[lane] = c;
            if (c & TOP_LEAF) {
                brt_top_lane_grow(n, lane, boxes + 6 * (size_t)(c & ~TOP_LEAF));
                continue;
            }
            for (k = 0; k < 4; k++) {
                float box[6];
                if (set->nodes[c].child[k] == TOP_EMPTY) continue;
                for (a = 0; a < 6; a++) box[a] = set->nodes[c].box[a][k];
                brt_top_lane_grow(n, lane, box);
            }
        }
    }
    for (i = 0; i < set->node_count; i++) brt_top_node_pad(&set->nodes[i]);
}

/* A loaded table's arrays, in one anonymous mapping, as the cache's blob
** buffers and for their reason (batchrt.c, "the geometry cache"): glibc
** keeps freed heap resident once its mmap threshold has grown, so tables
** loaded and evicted all render long would hold resident memory the
** budget no longer charges (make bench-island's render check saw it). */
static brt_result table_alloc(instance_set *set, uint32_t n, uint32_t m, uint32_t k)
{
    const size_t frames = (size_t)n * sizeof *set->frames, nodes = (size_t)m * sizeof *set->nodes;
    const size_t words = ((size_t)2 * n + k) * sizeof(uint32_t);   /* ids, prototypes, uses */
    unsigned char *at;
    set->count = n;
    set->node_count = m;
    set->use_count = k;
    set->mapping_bytes = nodes + frames + words;   /* nodes first: the strictest alignment */
    set->mapping = mmap(NULL, set->mapping_bytes, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (set->mapping == MAP_FAILED) {
        set->mapping = NULL;
        return BRT_ENOMEM;
    }
    at = set->mapping;
    set->nodes = (top_node *)(void *)at;
    set->frames = (brt_instance_frame *)(void *)(at + nodes);
    set->ids = (uint32_t *)(void *)(at + nodes + frames);
    set->prototypes = set->ids + n;
    set->uses = set->prototypes + n;
    return BRT_OK;
}

/* Opens point id's instance table (size bytes at data, checksum already
** checked): every field validated, the boxes recomputed. */
brt_result brt_instance_table_open(const brt_scene *s, uint32_t id, const unsigned char *data,
                                      uint64_t size, instance_set **out, brt_error *err)
{
    instance_set *set = calloc(1, sizeof *set);
    uint32_t n, m, k;
    unsigned char *marks = NULL;
    float *boxes = NULL;
    brt_result r = BRT_OK;
    *out = NULL;
    if (!set) return brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    if (size < INSTANCE_TABLE_HEADER || memcmp(data, INSTANCE_TABLE_MAGIC, 8) != 0) {
        free(set);
        return table_fail(s, id, err, "bad magic");
    }
    n = brt_get_le32(data + 8);
    m = brt_get_le32(data + 12);
    k = brt_get_le32(data + 16);
    if (n == 0 || m == 0 || m > n || k == 0 || k > n || n != s->points[id].instances ||
        size != instance_table_bytes(n, m, k))
        r = table_fail(s, id, err, "counts disagree with its size or its table entry");
    else if (table_alloc(set, n, m, k) != BRT_OK || !(marks = calloc((size_t)n + m, 1)) ||
             !(boxes = malloc(6 * (size_t)n * sizeof *boxes)))
        r = brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    brt_margin_begin(&set->margin, s->points[id].lo, s->points[id].hi);
    if (r == BRT_OK) r = table_uses(s, id, data + INSTANCE_TABLE_HEADER, set, err);
    data += INSTANCE_TABLE_HEADER + ((size_t)k * 4 + 7) / 8 * 8;
    if (r == BRT_OK) r = table_records(s, id, data, set, boxes, err);
    if (r == BRT_OK)
        r = table_tree(s, id, data + (size_t)n * INSTANCE_RECORD_BYTES, set, marks, marks + n, err);
    if (r == BRT_OK) table_boxes(set, boxes);
    free(marks);
    free(boxes);
    if (r != BRT_OK) {
        brt_set_free(set);
        free(set);
        return r;
    }
    *out = set;
    return BRT_OK;
}

