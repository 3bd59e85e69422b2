/*
** batchrt.c -- the out-of-core batched traversal of Pharr et al. 1997 with
** the conservative proxies of Molenaar and Eisemann 2020, and what it needs
** that is neither a BVH (bvh.c) nor a voxel proxy (svdag.c).
**
** The file reads in two parts.  Part I is the method, in the order a ray
** meets it; Part II is support, not the paper: files, input, statistics
** and utilities.  Each section opens with a comment on its design.
**
** PART I -- THE METHOD
**   the partition into batching points    median splits of triangle centres
**   the top-level BVH over batching points and its restartable walk
**                                          (one binary heap, shared with
**                                          the scheduler)
**   instances                              the level below a batching
**                                          point: instance sets, one
**                                          intersect_ray for every mode
**   the scene in memory                    the types the scheduler works on
**   ray queues and the scheduler           the paper's loop (schedule,
**                                          process_batch, walk_on,
**                                          proxy_test, settle), and
**                                          batchrt's layers, each named;
**                                          the same loop in one function,
**                                          without layers
**                                          (schedule_reference)
**   the geometry cache                         pread, LRU (SQLite's pcache
**                                          shape), and read-ahead
** PART II -- SUPPORT, NOT THE PAPER
**   the scene file                         format (little-endian), the out-
**                                          of-core build (spill file,
**                                          buckets, batching points, the
**                                          instance pass),
**                                          opening, validation at open, the
**                                          partition checker
**   threads                                the scheduler's loop in phases
**                                          (layers 4-5), and the direct
**                                          mode's chunks
**   the direct mode's world                an instanced scene in memory
**                                          (brt_world)
** Below this file: mesh.c (OBJ and PLY input), bvh.c, svdag.c, and base.c
** (rays and hits, statistics, errors, utilities, the pool of threads);
** internal.h draws the layers.
** The data flow is drawn once, in batchrt.h's opening comment.
*/
/* MAP_ANONYMOUS (POSIX.1-2024) for the geometry cache's buffers: glibc shows
** it only beyond the Makefile's _POSIX_C_SOURCE=200809L, hence this file's
** one feature macro (nothing else here uses what it adds). */
#define _DEFAULT_SOURCE
#include "internal.h"
/* The oracles and checkers the library holds for its tests; the hooks
** only when compiled with BRT_TESTING (testing.h). */
#include "testing.h"

/* Invariants are assert()ed, compiled in by make debug (BRT_DEBUG) only:
** in the release build they cost nothing. */
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

/* ##################################################################### */
/* PART I -- THE METHOD: out-of-core batched traversal                   */
/* ##################################################################### */
/*
** Pharr et al. 1997 with the proxies of Molenaar and Eisemann 2020, in the
** order of the data flow (drawn in batchrt.h): the partition into batching
** points, the top-level BVH and its walk, the scene in memory, the queues
** and the scheduler, the geometry cache.
*/

/* ---- median splits (the partition and the top-level build share them) -- */

/* Longest axis of the bounds of the points centres[3*ids[i]]. */
static int longest_axis(const float *centres, const uint32_t *ids, uint32_t n)
{
    float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    uint32_t i;
    int a, axis = 0;
    for (i = 0; i < n; i++)
        for (a = 0; a < 3; a++) {
            float c = centres[3 * (size_t)ids[i] + a];
            if (c < lo[a]) lo[a] = c;
            if (c > hi[a]) hi[a] = c;
        }
    for (a = 1; a < 3; a++)
        if (hi[a] - lo[a] > hi[axis] - lo[axis]) axis = a;
    return axis;
}

/* Orders ids by (centre on axis, id): a total order, so the split and
** hence the scene file are the same on every run and every libc. */
static int centre_before(const float *centres, int axis, uint32_t a, uint32_t b)
{
    float ca = centres[3 * (size_t)a + axis], cb = centres[3 * (size_t)b + axis];
    return ca < cb || (ca == cb && a < b);
}

/* Quickselect (Hoare 1961): afterwards ids[0..k) come before ids[k..n) in
** the order above.  Expected linear time; the pivot is a median of three. */
static void select_kth(const float *centres, int axis, uint32_t *ids, uint32_t n, uint32_t k)
{
    uint32_t lo = 0, hi = n;            /* the k-th lies in ids[lo..hi) */
    while (hi - lo > 1) {
        uint32_t a = ids[lo], b = ids[lo + (hi - lo) / 2], c = ids[hi - 1], pivot, i, store;
        pivot = centre_before(centres, axis, a, b)
                    ? (centre_before(centres, axis, b, c) ? b : (centre_before(centres, axis, a, c) ? c : a))
                    : (centre_before(centres, axis, a, c) ? a : (centre_before(centres, axis, b, c) ? c : b));
        /* Lomuto partition around the pivot id (moved to the end). */
        for (i = lo; ids[i] != pivot; i++) {}
        ids[i] = ids[hi - 1];
        ids[hi - 1] = pivot;
        for (store = lo, i = lo; i < hi - 1; i++)
            if (centre_before(centres, axis, ids[i], pivot)) {
                uint32_t t = ids[i]; ids[i] = ids[store]; ids[store] = t;
                store++;
            }
        ids[hi - 1] = ids[store];
        ids[store] = pivot;
        if (store == k) return;
        if (store < k) lo = store + 1;
        else hi = store;
    }
}

/* Splits ids[0..n) spatially: the first k go to one side (k in 1..n-1). */
static void median_split(const float *centres, uint32_t *ids, uint32_t n, uint32_t k)
{
    select_kth(centres, longest_axis(centres, ids, n), ids, n, k);
}

/* ---- the partition into batching points ------------------------------ */

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

static brt_result partition_push(partition *p, uint32_t first, uint32_t count)
{
    if (p->count == p->capacity) {
        batch_range *r = brt_grow(p->ranges, &p->capacity, (size_t)p->count + 1, sizeof *r);
        if (!r) return BRT_ENOMEM;
        p->ranges = r;
    }
    p->ranges[p->count].first = first;
    p->ranges[p->count].count = count;
    p->count++;
    return BRT_OK;
}

/* Top-down: split on the longest axis of the centroid bounds until each part
** holds at most batch_tris triangles.  The split point is a multiple of
** batch_tris near the middle, so parts are full and there are few of them
** (ceil(n / batch_tris) when the counts allow). */
static brt_result partition_split(partition *p, const float *centroids, uint32_t first,
                                  uint32_t count, uint32_t batch_tris)
{
    uint32_t parts, k;
    brt_result r;
    if (count <= batch_tris) return partition_push(p, first, count);
    parts = (uint32_t)(((uint64_t)count + batch_tris - 1) / batch_tris);
    k = (uint32_t)(((uint64_t)parts / 2) * batch_tris);
    median_split(centroids, p->order + first, count, k);
    /* Both sides are smaller and k is near the middle: depth O(log n). */
    r = partition_split(p, centroids, first, k, batch_tris);
    if (r == BRT_OK) r = partition_split(p, centroids, first + k, count - k, batch_tris);
    return r;
}

/* Instances are partitioned the same way, by the centres of their world
** boxes, but a batching point's size is what its load reads: the
** triangles of the distinct prototypes it references, each counted once,
** as pandora counts them.  A range is split at its median while it is
** larger than batch_tris and references more than one prototype: a
** prototype larger than batch_tris then gets points of its own instances,
** its blob shared by them all and cached once (splitting the prototype
** into pieces, as pandora does, would save no bytes: each piece would
** still be read whole).  Optionally (brt_scene_options.batch_instanced)
** a range is split too while its instances hold more triangles than that,
** which gives points of the paper's sizes (10-25 M instanced triangles)
** whatever the prototypes.  size_of(user, ids, n, &distinct, &instanced)
** measures a range. */
typedef uint64_t (*range_size_fn)(void *user, const uint32_t *ids, uint32_t n,
                                  uint32_t *distinct, uint64_t *instanced);

typedef struct size_limits {
    uint32_t batch_tris;          /* distinct prototype triangles */
    uint64_t batch_instanced;     /* instanced triangles; 0: none */
} size_limits;

static brt_result partition_by_size(partition *p, const float *centres, uint32_t first,
                                    uint32_t count, const size_limits *limits,
                                    range_size_fn size_of, void *user)
{
    uint32_t distinct, k = count / 2;
    uint64_t instanced, unique;
    brt_result r;
    if (count <= 1) return partition_push(p, first, count);
    unique = size_of(user, p->order + first, count, &distinct, &instanced);
    if ((unique <= limits->batch_tris || distinct <= 1) &&
        (limits->batch_instanced == 0 || instanced <= limits->batch_instanced))
        return partition_push(p, first, count);
    median_split(centres, p->order + first, count, k);
    r = partition_by_size(p, centres, first, k, limits, size_of, user);
    if (r == BRT_OK) r = partition_by_size(p, centres, first + k, count - k, limits, size_of, user);
    return r;
}

/* ---- one binary heap (the top-level walk and the scheduler share it) -- */
/*
** A binary min-heap (Williams 1964) of 64-bit keys whose low word names
** the item.  Each user packs its whole order into the key, so one integer
** compare decides: the walk, subtrees and batching points by entry
** distance (walk_key_of); the scheduler, batching points by queue length
** (queue_key).  Ties fall to the lower item number, so the order is total
** and what comes out first never depends on the heap's inner layout.
** With pos (the scheduler) pos[item] is the item's place or HEAP_ABSENT,
** for a key lowered in place (a queue grew); the walk passes pos = NULL.
*/
#define HEAP_ABSENT 0xFFFFFFFFu

typedef struct key_heap {
    uint64_t *keys;
    uint32_t *pos;              /* per item: its index in keys, or HEAP_ABSENT; or NULL */
    uint32_t size;
} key_heap;

static inline void heap_place(key_heap *h, uint32_t i, uint64_t key)
{
    h->keys[i] = key;
    if (h->pos) h->pos[(uint32_t)key] = i;
}

/* Invariant (make debug): the heap order holds around place i, where a
** push or a pop left a key: no smaller than its parent's, no larger than
** its children's, and pos (when kept) points back at it. */
#ifndef NDEBUG
static int heap_ordered_at(const key_heap *h, uint32_t i)
{
    uint32_t c = 2 * i + 1;
    if (i >= h->size) return 1;
    if (i > 0 && h->keys[(i - 1) / 2] > h->keys[i]) return 0;
    if (c < h->size && h->keys[c] < h->keys[i]) return 0;
    if (c + 1 < h->size && h->keys[c + 1] < h->keys[i]) return 0;
    return !h->pos || h->pos[(uint32_t)h->keys[i]] == i;
}
#endif

/* Puts key at hole i or above it (every key above i is no larger). */
static inline void heap_up(key_heap *h, uint32_t i, uint64_t key)
{
    while (i > 0 && key < h->keys[(i - 1) / 2]) {
        heap_place(h, i, h->keys[(i - 1) / 2]);
        i = (i - 1) / 2;
    }
    heap_place(h, i, key);
    assert(heap_ordered_at(h, i));
}

static inline void heap_push(key_heap *h, uint64_t key)
{
    heap_up(h, h->size++, key);
}

/* Inserts key's item, or lowers the key of the item already there (pos). */
static void heap_lower(key_heap *h, uint64_t key)
{
    uint32_t at = h->pos[(uint32_t)key];
    heap_up(h, at == HEAP_ABSENT ? h->size++ : at, key);
}

/* Removes and returns the least key. */
static inline uint64_t heap_pop(key_heap *h)
{
    uint64_t top = h->keys[0], last = h->keys[--h->size];
    uint32_t i = 0;
    if (h->pos) h->pos[(uint32_t)top] = HEAP_ABSENT;
    if (h->size == 0) return top;
    for (;;) {
        uint32_t c = 2 * i + 1;
        if (c >= h->size) break;
        if (c + 1 < h->size && h->keys[c + 1] < h->keys[c]) c++;
        if (h->keys[c] >= last) break;
        heap_place(h, i, h->keys[c]);
        i = c;
    }
    heap_place(h, i, last);
    assert(heap_ordered_at(h, i) && top <= h->keys[0]);
    return top;
}

/* ---- the top-level BVH over batching points and its restartable walk -- */
/*
** A 4-wide BVH over the batching points' boxes (the paper's top level is
** 4-wide too).  It lives here, beside the partition whose median split it
** shares, and tests boxes with bvh.c's brt_box_span4 so that its distances
** agree bit for bit with the triangle BVHs.
** Why a node type of its own (top_node) beside bvh.c's qnode, both 4-wide:
** a qnode holds 8-bit planes in a frame of its own and triangle leaves, in
** the blobs that the disk reads (its size is the bytes read); a top_node
** holds float boxes of batching points, stored as is in the scene file's
** top-level section (TOP_NODE_BYTES) and checked at open against the batch
** table (check_top: nested, ordered, finite).  One node type would change
** that section's bytes, which this consolidation keeps.  The two share the
** box test (brt_box_span4) and the median split; the top level has about
** one node per three batching points, so its float boxes cost little.
**
** A ray's place in its walk is one 8-byte key (t_entry, id): the entry
** distance into the last batching point it was queued at, and that
** point's id.  A walk (top_walk) visits the batching points the ray enters
** no later than tlimit in key order, best first: a min-heap holds the
** subtrees and batching points met so far by their entry distance, and
** the nearest is expanded or, for a batching point, handed out.  Exact,
** because a box inside another is entered no sooner (the box test is
** monotone in the box bounds), and at equal distances subtrees come out
** before batching points, and batching points by id.  One walk serves a
** ray for as long as it passes batching points in memory or culled by
** their proxies; queued, it keeps only its key, and the next walk starts
** again at the root, skipping
**  (a) subtrees the ray leaves before the key's t: every box inside is
**      entered no later than it is left, so its key would be smaller,
** and the batching points at or before the key.  Why one walk and not a
** fresh descent from the root per batching point: a ray passing many
** resident or culled points would repeat the descent at each.
*/
#define TOP_EMPTY 0xFFFFFFFFu   /* an unused child slot: never entered */
#define TOP_LEAF 0x80000000u    /* child code of batching point (code & ~TOP_LEAF) */
#define TOP_NODE_BYTES 112

typedef struct top_node {
    float box[6][4];            /* child boxes: rows min x, y, z, max x, y, z; one lane
                                ** per child (grown in memory; brt_box_span4's layout) */
    uint32_t child[4];          /* node index (> own index), TOP_LEAF|id, TOP_EMPTY */
} top_node;

typedef struct walk_key {
    float t;
    uint32_t id;                /* TOP_EMPTY before the first batching point */
} walk_key;

static int key_after(float t, uint32_t id, walk_key last)
{
    return last.id == TOP_EMPTY || t > last.t || (t == last.t && id > last.id);
}

typedef struct top_builder {
    const float *boxes;         /* 6 floats per batching point: lo, hi */
    const float *centres;       /* 3 floats per batching point */
    top_node *nodes;
    uint32_t count;
} top_builder;

static void top_lane_clear(top_node *node, int lane)
{
    int a;
    node->child[lane] = TOP_EMPTY;
    for (a = 0; a < 3; a++) {
        node->box[a][lane] = INFINITY;
        node->box[3 + a][lane] = -INFINITY;
    }
}

static void top_lane_grow(top_node *node, int lane, const float *box)
{
    int a;
    for (a = 0; a < 3; a++) {
        if (box[a] < node->box[a][lane]) node->box[a][lane] = box[a];
        if (box[3 + a] > node->box[3 + a][lane]) node->box[3 + a][lane] = box[3 + a];
    }
}

static uint32_t top_build_node(top_builder *b, uint32_t *ids, uint32_t n)
{
    uint32_t index = b->count++, first[5], groups = 1, g, i;
    first[0] = 0;
    first[1] = n;
    /* Split the largest group at its median until there are four: two
    ** levels of a binary median split collapsed into one node. */
    while (groups < 4) {
        uint32_t big = 0, size;
        for (g = 1; g < groups; g++)
            if (first[g + 1] - first[g] > first[big + 1] - first[big]) big = g;
        size = first[big + 1] - first[big];
        if (size < 2) break;
        median_split(b->centres, ids + first[big], size, size / 2);
        memmove(first + big + 2, first + big + 1, (groups - big) * sizeof *first);
        first[big + 1] = first[big] + size / 2;
        groups++;
    }
    for (g = 0; g < 4; g++) top_lane_clear(&b->nodes[index], (int)g);
    for (g = 0; g < groups; g++) {
        uint32_t size = first[g + 1] - first[g];
        uint32_t child = size == 1 ? (TOP_LEAF | ids[first[g]])
                                   : top_build_node(b, ids + first[g], size);
        b->nodes[index].child[g] = child;
        for (i = first[g]; i < first[g + 1]; i++)
            top_lane_grow(&b->nodes[index], (int)g, b->boxes + 6 * (size_t)ids[i]);
    }
    return index;
}

/* Builds the nodes (at most count of them: every node has two or more
** children, except a root over a single batching point). */
static brt_result top_build(const float *boxes, uint32_t count, top_node **nodes,
                            uint32_t *node_count)
{
    top_builder b;
    uint32_t *ids = malloc((size_t)count * sizeof *ids), i;
    float *centres = malloc(3 * (size_t)count * sizeof *centres);
    b.nodes = malloc((size_t)count * sizeof *b.nodes);
    if (!ids || !centres || !b.nodes) {
        free(ids); free(centres); free(b.nodes);
        return BRT_ENOMEM;
    }
    for (i = 0; i < count; i++) {
        int a;
        ids[i] = i;
        for (a = 0; a < 3; a++)
            centres[3 * (size_t)i + a] = 0.5f * boxes[6 * (size_t)i + a] + 0.5f * boxes[6 * (size_t)i + 3 + a];
    }
    b.boxes = boxes;
    b.centres = centres;
    b.count = 0;
    top_build_node(&b, ids, count);
    free(ids);
    free(centres);
    *nodes = b.nodes;
    *node_count = b.count;
    return BRT_OK;
}

/* The heap holds each node and batching point at most once (check_top
** makes sure every node has one parent), so nodes + points keys do.  An
** entry is a subtree (node index) or a batching point (TOP_LEAF | id)
** with the distance the ray enters its box (walk_key_of). */
typedef key_heap top_walk;

/* Heap order: nearer first; at equal entry, subtrees (codes without
** TOP_LEAF) before batching points, batching points by id.  The entry
** goes to the high word as an unsigned integer that orders as the float
** does (sign-magnitude to offset binary; -0 as +0, which compare equal).
** Never NaN: a box is entered only when entry <= exit. */
static uint64_t walk_key_of(float entry, uint32_t code)
{
    uint32_t bits;
    if (entry == 0.0f) entry = 0.0f;
    memcpy(&bits, &entry, 4);
    bits = bits & 0x80000000u ? ~bits : bits | 0x80000000u;
    return (uint64_t)bits << 32 | code;
}

static float walk_entry_of(uint64_t key)
{
    uint32_t bits = (uint32_t)(key >> 32);
    float entry;
    bits = bits & 0x80000000u ? bits & 0x7FFFFFFFu : ~bits;
    memcpy(&entry, &bits, 4);
    return entry;
}

static void top_walk_start(top_walk *w)
{
    w->size = 0;
    heap_push(w, walk_key_of(-INFINITY, 0));   /* the root node; its children get box tests */
}

/* Pushes the children of node that the ray enters no later than tlimit
** and does not leave before the key's t, (a). */
static void walk_expand(top_walk *w, const top_node *node, const brt_box_lanes *ray, float tnear,
                        float tlimit, walk_key key)
{
    float entries[4], exits[4];
    unsigned lanes = brt_box_span4(ray, node->box, tnear, tlimit, entries, exits);
    int lane;
    for (lane = 0; lane < 4; lane++) {
        if (node->child[lane] == TOP_EMPTY || !(lanes & (1u << lane))) continue;
        if (key.id != TOP_EMPTY && exits[lane] < key.t) continue;             /* (a) */
        heap_push(w, walk_key_of(entries[lane], node->child[lane]));
    }
}

/* The next batching point after *key that the ray enters no later than
** tlimit (which may have shrunk since the last call): 1 and *key updated,
** or 0 when there is none.  Invariants (make debug): what the heap hands
** out only grows (a box inside another is entered no sooner), so walk
** keys only grow, and a batching point handed out is entered by tlimit. */
static int top_walk_next(top_walk *w, const top_node *nodes, const brt_box_lanes *ray, float tnear,
                         float tlimit, walk_key *key)
{
    const uint64_t stop = walk_key_of(tlimit, 0xFFFFFFFFu);   /* entry <= tlimit */
    uint64_t last = 0;
    while (w->size > 0 && w->keys[0] <= stop) {
        uint64_t next = heap_pop(w);
        uint32_t code = (uint32_t)next;
        float entry = walk_entry_of(next);
        assert(next >= last);
        last = next;
        (void)last;                     /* read by the assert only */
        if (code & TOP_LEAF) {
            uint32_t id = code & ~TOP_LEAF;
            if (!key_after(entry, id, *key)) continue;
            assert(entry <= tlimit);
            key->t = entry;
            key->id = id;
            return 1;
        }
        walk_expand(w, &nodes[code], ray, tnear, tlimit, *key);
    }
    return 0;
}

/* ---- instances: the level below a batching point ---------------------- */
/*
** A batching point of an instanced scene holds world triangles (one
** triangle BVH) and instances of prototypes (each prototype one triangle
** BVH, shared by all its instances and, in batched mode, by all batching
** points).  The instances sit under the same 4-wide box tree as the
** batching points (top_build, over their world boxes), descended here
** depth first, nearest child first, and pruned by the closest hit so far.
** Its boxes are tested grown by the margin of bvh.c ("Instances"), so the
** rounding of the ray's transform never prunes a hit.  direct mode (a
** brt_world) and batched mode intersect through the same function,
** intersect_ray (closest hit or, for an occlusion ray, any hit), so they
** write the same bytes.
*/
static void top_node_pad(top_node *n);
static void hit_mark_occluded(brt_hit *hit);

/* The margin of a box of instances (bvh.c, "Instances"), taken about the
** box's centre, so that it is as small as the box's neighbourhood allows
** wherever the box lies: the largest condition number of its instances,
** and the largest |d - center| + radius (brt_instance_bounds). */
typedef struct instance_margin {
    float condition, reach;
    float center[3];
} instance_margin;

static float margin_of(const instance_margin *m, const brt_ray *ray)
{
    return brt_instance_margin(m->condition, m->reach, m->center, ray);
}

/* Starts a margin about the centre of the box lo..hi (no instances yet). */
static void margin_begin(instance_margin *m, const float lo[3], const float hi[3])
{
    int a;
    m->condition = m->reach = 0.0f;
    for (a = 0; a < 3; a++) m->center[a] = 0.5f * lo[a] + 0.5f * hi[a];
}

/* Takes in an instance: its frame and its radius. */
static void margin_add(instance_margin *m, const brt_instance_frame *f, float radius)
{
    double far = 0.0;
    float reach;
    int a;
    for (a = 0; a < 3; a++)
        if (fabs(f->translation[a] - m->center[a]) > far) far = fabs(f->translation[a] - m->center[a]);
    reach = nextafterf((float)((far + radius) * (1.0 + 0x1p-20)), INFINITY);   /* rounded up */
    if (reach > m->reach) m->reach = reach;
    if (f->condition > m->condition) m->condition = f->condition;
}

typedef struct instance_set {
    uint32_t count;
    uint32_t *ids;                  /* the instances' numbers (hit.inst) */
    uint32_t *prototypes;           /* their prototypes */
    brt_instance_frame *frames;
    top_node *nodes;                /* boxes grown by top_node_pad */
    uint32_t node_count;
    instance_margin margin;         /* about the centre of all their boxes */
    uint32_t *uses;                 /* batched mode: the distinct prototypes, */
    uint32_t use_count;             /* ascending (what a load must make resident) */
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

typedef struct set_entry {
    uint32_t code;                  /* node index, or TOP_LEAF | instance slot */
    float entry;
} set_entry;

/* Pushes the children of node the ray enters by tlimit, farthest first,
** so the nearest is popped next. */
static int set_expand(const top_node *node, const brt_box_lanes *ray, float tnear, float tlimit,
                      set_entry *stack, int sp)
{
    float entries[4], exits[4];
    const unsigned lanes = brt_box_span4(ray, node->box, tnear, tlimit, entries, exits);
    int order[4], n = 0, i, j;
    for (i = 0; i < 4; i++) {
        if (node->child[i] == TOP_EMPTY || !(lanes & (1u << i))) continue;
        for (j = n++; j > 0 && entries[order[j - 1]] < entries[i]; j--) order[j] = order[j - 1];
        order[j] = i;
    }
    for (i = 0; i < n; i++) {
        assert(sp < SET_STACK);
        stack[sp].code = node->child[order[i]];
        stack[sp++].entry = entries[order[i]];
    }
    return sp;
}

/* Closest hit (any_hit = 0) or any hit (any_hit = 1, returns 1) among the
** instances of set. */
static int set_trace(const geometry *g, const brt_ray *ray, brt_hit *hit, float normal[3],
                     int any_hit)
{
    const instance_set *set = g->instances;
    set_entry stack[SET_STACK];
    brt_ray_prep prep;
    brt_box_lanes lanes;
    int sp = 0;
    if (!set || set->node_count == 0) return 0;
    if (set->count == 1) {   /* one instance: its prototype's root box is the only test needed */
        const brt_bvh *proto = g->prototypes[set->prototypes[0]];
        if (any_hit) return brt_instance_occluded(proto, &set->frames[0], ray);
        brt_instance_intersect(proto, &set->frames[0], set->ids[0], ray, hit, normal);
        return 0;
    }
    brt_ray_prepare_margin(ray, margin_of(&set->margin, ray), &prep);
    if (!prep.valid) return 0;
    brt_box_lanes_of(&prep, &lanes);
    stack[sp].code = 0;
    stack[sp++].entry = ray->tnear;
    while (sp > 0) {
        const set_entry e = stack[--sp];
        const float tlimit = !any_hit && hit->t < ray->tfar ? hit->t : ray->tfar;
        if (e.entry > tlimit) continue;
        if (!(e.code & TOP_LEAF)) {
            sp = set_expand(&set->nodes[e.code], &lanes, ray->tnear, tlimit, stack, sp);
            continue;
        } else {
            const uint32_t k = e.code & ~TOP_LEAF;
            const brt_bvh *proto = g->prototypes[set->prototypes[k]];
            if (!any_hit)
                brt_instance_intersect(proto, &set->frames[k], set->ids[k], ray, hit, normal);
            else if (brt_instance_occluded(proto, &set->frames[k], ray))
                return 1;
        }
    }
    return 0;
}

/* A ray prepared for the box tests, as the top-level walk holds it: a
** batching point's BVH walks it without preparing it again, when it was
** prepared without a margin, i.e. exactly as the BVH would.  (With the
** margin of instances its boxes are grown: still conservative, but the
** triangle clamp would use the grown box, and a t could round apart from
** the direct mode's; make mutants cannot tell, so the rule is kept by
** construction: walk_on passes NULL then.) */
typedef struct prepared_ray {
    brt_ray_prep prep;
    brt_box_lanes lanes;
} prepared_ray;

/* A BVH's closest hit (and normal, unless NULL) or, with any, whether it
** occludes: of the prepared ray p when there is one. */
static int triangles_walk(const brt_bvh *bvh, const brt_ray *ray, const prepared_ray *p,
                          brt_hit *hit, float normal[3], int any)
{
    if (p) return brt_bvh_walk_prepared(bvh, ray, &p->prep, &p->lanes, hit, normal, any);
    if (any) return brt_bvh_occluded(bvh, ray);
    brt_bvh_intersect_normal(bvh, ray, hit, normal);
    return 0;
}

/* The record of brt_ray_source for one ray against geometry: the closest
** hit so far (and its normal, unless NULL), or for an occlusion ray t = 0,
** prim = 0 once anything is hit in [tnear, tfar].  Direct mode and the
** scheduler share it, so both kinds give the same bytes in every mode.
** p: the ray already prepared (prepared_ray), or NULL. */
static void intersect_ray(const geometry *g, const brt_ray *ray, uint64_t tag, brt_hit *hit,
                          float normal[3], const prepared_ray *p)
{
    if (tag & BRT_TAG_OCCLUSION) {
        if ((g->triangles && triangles_walk(g->triangles, ray, p, NULL, NULL, 1)) ||
            set_trace(g, ray, hit, NULL, 1))
            hit_mark_occluded(hit);
        return;
    }
    if (g->triangles) triangles_walk(g->triangles, ray, p, hit, normal, 0);
    set_trace(g, ray, hit, normal, 0);
}

/* The one check of an instance as a scene source hands it over (the
** direct mode's world and the build both): its prototype in range, its
** transform accepted by brt_instance_frame_init, whose frame it returns. */
static brt_result instance_admit(const brt_instance *in, uint32_t number, uint32_t prototypes,
                                 brt_instance_frame *frame, brt_error *err)
{
    if (in->prototype >= prototypes)
        return brt_fail(err, BRT_EARG, "instance %u: prototype %u out of range (%u prototypes)",
                        (unsigned)number, (unsigned)in->prototype, (unsigned)prototypes);
    return brt_instance_frame_init(in, number, frame, err);
}

/* Builds the box tree over a set's instances, whose world boxes are
** boxes[6i..6i+5] (lo, hi). */
static brt_result set_build_tree(instance_set *set, const float *boxes)
{
    uint32_t i;
    set->nodes = NULL;
    set->node_count = 0;
    if (set->count == 0) return BRT_OK;
    if (top_build(boxes, set->count, &set->nodes, &set->node_count) != BRT_OK) return BRT_ENOMEM;
    for (i = 0; i < set->node_count; i++) top_node_pad(&set->nodes[i]);
    return BRT_OK;
}

/* The set's margin, about the centre of its instances' boxes. */
static void set_fit_margin(instance_set *set, const float *boxes, const float *radii)
{
    float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    uint32_t i;
    int a;
    for (i = 0; i < set->count; i++)
        for (a = 0; a < 3; a++) {
            if (boxes[6 * (size_t)i + a] < lo[a]) lo[a] = boxes[6 * (size_t)i + a];
            if (boxes[6 * (size_t)i + 3 + a] > hi[a]) hi[a] = boxes[6 * (size_t)i + 3 + a];
        }
    margin_begin(&set->margin, lo, hi);
    for (i = 0; i < set->count; i++) margin_add(&set->margin, &set->frames[i], radii[i]);
}

static void set_free(instance_set *set)
{
    free(set->uses);
    free(set->ids);
    free(set->prototypes);
    free(set->frames);
    free(set->nodes);
    memset(set, 0, sizeof *set);
}

/* ---- the scene in memory ---------------------------------------------- */
/*
** What the scheduler works on.  An open scene (struct brt_scene) holds the
** scene file's small parts in memory -- per batching point its box, blob
** place and proxies (batch_entry), the top-level nodes, the DAG pool --
** and leaves the blobs on disk.  The geometry cache keeps some blobs
** resident (cache_entry per batching point).  The code that fills these
** structures is in Part II (the scene file).
*/
typedef struct batch_entry {
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
} batch_entry;

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
    uint32_t batch_tris, proxy_res, batch_count, triangle_count, top_node_count;
    section sections[4];        /* the fourth: prototypes (instanced files) */
    /* Instanced scenes (version 4) only: */
    uint32_t prototype_count, instance_count;
    uint64_t instanced_triangles;
    instance_margin margin;     /* of all instances: the walk's */
    uint64_t batch_instanced;   /* brt_scene_options.batch_instanced */
} scene_header;

/* A blob opened: a BVH (a point of world triangles, or a prototype) or
** an instance table (a point of instances), referring into the blob. */
typedef struct blob_view {
    brt_bvh *bvh;
    instance_set *set;
} blob_view;

/* One blob while a trace runs -- a batching point's or a prototype's --
** and the geometry cache's state for it (SQLite's pcache shape: fetch
** pins, release unpins, only unpinned entries are evicted, least recently
** used first). */
typedef struct cache_entry {
    void *data;                 /* page-aligned copy of the blob, or NULL */
    blob_view view;             /* into data */
    geometry geometry;          /* a batching point's, for intersect_ray */
    uint64_t bytes;             /* what data holds (page-rounded) and the
                                ** resident layout decoded of it (decoded) */
    uint64_t decoded;
    uint32_t pins;
    uint32_t lru_prev, lru_next;   /* unpinned resident entries; NO_ENTRY ends */
} cache_entry;

#define NO_ENTRY 0xFFFFFFFFu

/* Where a blob lies: the blobs are the batching points' (ids 0 ..
** batch_count - 1) and then the prototypes'. */
typedef struct blob_place {
    uint64_t offset, size, checksum;
} blob_place;

struct brt_scene {
    char *path;
    int fd;
    scene_header header;
    batch_entry *batches;
    proto_entry *prototypes;    /* instanced scenes, else NULL */
    blob_place *blobs;          /* batch_count + prototype_count */
    top_node *top;
    brt_svdag *dag;
    void *dag_blob;             /* the pool refers to it */
    uint64_t file_size;
};

typedef struct geometry_cache {
    brt_scene *scene;
    cache_entry *entries;       /* per blob: batching points, then prototypes */
    uint32_t entry_count;
    const brt_bvh **prototypes; /* per prototype: its BVH while resident, else NULL */
    uint32_t working_set;       /* blobs the last fetch needed (cache_check) */
    uint64_t budget, held;
    uint64_t all_bytes;         /* cache_bytes of every blob at once */
    uint64_t decoded;           /* resident layouts held (layer 9) */
    int decode;                 /* layer 9 on (not no_decode) */
    uint32_t lru_head, lru_tail;   /* least recently used first */
    brt_read_fn read_fn;
    void *read_user;
    int drop_os_cache;          /* brt_trace_options.drop_os_cache */
    brt_stats *stats;
    /* Read-ahead (more than one thread): one blob read by a thread of its
    ** own while the scheduler's threads intersect (cache_read_ahead). */
    int read_ahead;
    int ahead_running;
    pthread_t ahead_thread;
    uint32_t ahead_id;          /* NO_ENTRY: none */
    void *ahead_data;
    blob_view ahead_view;
    uint64_t ahead_bytes;
    double ahead_seconds;
    brt_result ahead_result;
} geometry_cache;

#define SCENE_PAGE 4096u   /* blobs start at multiples of it (the scene file) */

/* The geometry cache's interface: its section follows the scheduler's. */
static brt_result cache_init(geometry_cache *c, brt_scene *scene, uint64_t budget,
                             const brt_trace_options *opt, brt_stats *stats);
static void cache_free(geometry_cache *c);
static brt_result cache_fetch(geometry_cache *c, uint32_t id, const geometry **g, brt_error *err);
static const geometry *cache_peek(const geometry_cache *c, uint32_t id);
static void cache_touch(geometry_cache *c, uint32_t id);
static void cache_release(geometry_cache *c, uint32_t id);
static void cache_release_blob(geometry_cache *c, uint32_t id);
static void cache_read_ahead(geometry_cache *c, uint32_t id);
static brt_result cache_check(const geometry_cache *c, brt_error *err);
static brt_result blob_read(const geometry_cache *c, uint32_t id, uint64_t *bytes_read, void **data,
                            blob_view *view, brt_error *err);
static void view_free(blob_view *view);
static brt_result instance_table_open(const brt_scene *s, uint32_t id, const unsigned char *data,
                                      uint64_t size, instance_set **out, brt_error *err);
static void blob_free(const brt_scene *scene, uint32_t id, void *data);
static uint64_t cache_bytes(const brt_scene *scene, uint32_t id);

/* From Part II: reading the scene file, one ray through one BVH (the
** direct mode), page rounding. */
static brt_result read_fully(int fd, void *buf, size_t size, uint64_t offset,
                             brt_read_fn read_fn, void *user, uint64_t *bytes_read,
                             const char *path, brt_error *err);
static long pread_reader(int fd, void *buf, size_t size, uint64_t offset, void *user);
static uint64_t round_up_page(uint64_t n);

/* ---- ray queues and the scheduler ------------------------------------ */
/*
** THE PAPER'S SCHEDULER (Pharr et al. 1997, as Molenaar and Eisemann
** 2020 use it with proxies) is the plain loop of this section, with one
** thread:
**   schedule       take new rays (refill); then, while a queue is not
**                  empty, process the fullest (key_heap, queue_key), and
**                  take new rays again
**   process_batch  fetch its batching point through the LRU geometry
**                  cache (cache_fetch), intersect each ray of its queue
**                  there, release the point, and let each ray walk on
**   walk_on        the ray's top-level walk: at the next batching point it
**                  enters whose proxy it hits (proxy_test) it stops
**   settle         a stopped ray is queued there (enqueue); a ray whose
**                  walk is over is finished and its slot takes a new ray
** Each disk read serves as many rays as it can: the fullest queue first.
** schedule_reference (below, before trace_source) is the same loop with
** no layer written as one function, for reading first.
**
** batchrt's improvements are LAYERS on that loop: each is one named
** function that the loop calls, and each says why it is there and which
** command measures it.
**   1. intersect_resident  geometry in memory: intersect at once, no queue
**   2. proxies_pay         no proxy tests when the budget holds every blob
**   3. exact_proxy_hit     analysis: the triangles themselves as the proxy
**   4. cache_read_ahead    threads: the next load read while a phase runs
**   5. phases_run          threads: the loop's rays walked in parallel and
**                          settled in order (Part II, "Threads")
**   6. fetch_for           statistics: the loads only shadow rays asked for
**   7. inner_stops         inner proxies: an occlusion ray settled occluded
**                          without a queue (the paper's future work)
**   8. forward, take_rays  other processes (brt_exchange): a ray stopping
**                          at a point owned elsewhere is sent there, and
**                          rays sent here are queued where they stopped
**   9. cache_decode        in core: a point loaded is decoded to float
**                          nodes when the budget holds it beside every blob
**  10. rays_in_flight      in core: few rays in flight by default
** paper_scheduler turns layers 1 and 2 off (what make figures measures as
** the paper's scheduler); exact_proxies turns 3 on; one thread turns 4
** and 5 off; no_inner turns 7 off; no_decode turns 9 off.  No layer
** changes a hit; 1-3 and 7 change which loads happen, 4-6, 9 and 10 none
** (the threads: tests hold the phases byte-equal to the plain loop).
**
** Rays in flight live in slots; a queue per batching point holds slot
** numbers; a min-heap of queue keys (key_heap) orders the non-empty
** queues, longest first, ties to the lowest id.
**
** Per-ray state while queued (ray_slot): the ray, its closest hit so far
** and that triangle's normal, its walk key, the number of batching points
** it was queued at and the caller's tag.  The tag also says the ray's
** kind (BRT_TAG_OCCLUSION), so an occlusion ray costs no byte more: it
** keeps an unused normal, and its hit record turns from the miss record
** into "occluded" at its first hit.
*/
typedef struct ray_slot {
    brt_ray ray;
    brt_hit hit;
    float normal[3];
    walk_key key;
    uint32_t visits;
    uint64_t tag;
} ray_slot;

typedef struct ray_queue {
    uint32_t *slots;
    uint32_t count;
    size_t capacity;
} ray_queue;

/* The threaded variant's state (layers 4 and 5) and its record of the
** resident batching points a walk used: Part II, "Threads". */
typedef struct phase_threads phase_threads;
typedef struct use_log use_log;

/* What one walk needs of its own: the heap of its top-level walk, its
** counters (added to the statistics after each batch), and where its uses
** of resident batching points go for the LRU order: straight to the cache
** in the plain loop (cache), or to a log that the threaded variant
** replays in the order the plain loop would have made them (uses). */
typedef struct walker {
    top_walk walk;
    uint64_t resident_visits, proxy_tests, proxy_culled;
    uint64_t inner_stopped;     /* occlusion rays an inner proxy settled */
    geometry_cache *cache;      /* the plain loop; NULL: log the uses */
    use_log *uses;
} walker;

typedef struct scheduler {
    brt_scene *scene;
    const brt_ray_source *source;
    int use_proxies, paper_scheduler;
    int use_inner;              /* consult the inner proxies (not no_inner) */
    brt_stats *stats;
    geometry_cache cache;
    ray_slot *slots;
    uint32_t *free_slots, free_count, capacity;
    ray_queue *queues;
    key_heap fullest;                       /* the non-empty queues (queue_key) */
    walker walker;                          /* the plain loop's walk */
    phase_threads *threads;                 /* layers 4-5; NULL: one thread */
    geometry *exact;                        /* exact_proxies: every point's, or NULL */
    blob_view *exact_views;                 /* every blob's, opened */
    void **exact_data;
    const brt_bvh **exact_prototypes;
    brt_ray *incoming;
    uint64_t *incoming_tags;
    uint32_t *fresh;                        /* the slots refill just filled */
    const brt_trace_options *follow;        /* trace --follow: steps reported, or NULL */
    const volatile sig_atomic_t *interrupt; /* brt_trace_options.interrupt */
    uint64_t fetch_bytes;                   /* bytes the last fetch read (its step) */
    const brt_exchange *exchange;           /* layer 8, or NULL */
    brt_ray_state *arrivals;                /* rays received (layer 8) */
} scheduler;

/* The threaded variant, Part II. */
static brt_result threads_init(scheduler *s, unsigned threads);
static void threads_free(scheduler *s);
static brt_result phases_run(scheduler *s, const uint32_t *slots, uint32_t count, uint32_t id,
                             const geometry *g);
static void use_log_record(use_log *log, uint32_t id);

/* ---- following one ray (trace --follow) ---- */

/* Reports a step of ray r when it is the ray followed (brt_trace_options
** follow_tag); costs one compare otherwise. */
static void follow_step(const scheduler *s, const ray_slot *r, brt_step_kind kind, uint32_t point,
                        float t)
{
    brt_step step;
    if (!s->follow || r->tag != s->follow->follow_tag) return;
    step.kind = kind;
    step.point = point;
    step.t = t;
    step.bytes = kind == BRT_STEP_LOAD ? s->fetch_bytes : 0;
    step.hit = r->hit;
    step.visits = r->visits;
    s->follow->follow(s->follow->follow_user, r->tag, &step);
}

/* Heap order: the fullest queue first (the key's high word falls as the
** queue grows), at equal lengths the lowest id. */
static uint64_t queue_key(uint32_t count, uint32_t id)
{
    return (uint64_t)(UINT32_MAX - count) << 32 | id;
}

static int is_occlusion(const ray_slot *r)
{
    return (r->tag & BRT_TAG_OCCLUSION) != 0;
}

/* An occlusion ray is done at its first hit; a closest-hit ray only when
** its walk ends. */
static int found_occluder(const ray_slot *r)
{
    return is_occlusion(r) && r->hit.prim != BRT_NO_PRIM;
}

/* The record of an occluded occlusion ray (brt_ray_source): t = 0,
** prim = 0, u = v = 0 kept from the miss record it starts as. */
static void hit_mark_occluded(brt_hit *hit)
{
    hit->t = 0.0f;
    hit->prim = 0;
}

/* How far the walk goes: the closest hit so far, or tfar.  (An occlusion
** ray's record stays the miss record, t = +inf, until it ends the walk.) */
static float walk_limit(const ray_slot *r)
{
    return r->hit.t < r->ray.tfar ? r->hit.t : r->ray.tfar;
}

/* Intersects a ray with a batching point's triangles: the closest hit so
** far, or for an occlusion ray any hit in [tnear, tfar] (the record of
** brt_ray_source: t = 0, prim = 0 when occluded). */
static void intersect_slot(const scheduler *s, const geometry *g, ray_slot *r, const prepared_ray *p)
{
    intersect_ray(g, &r->ray, r->tag, &r->hit, r->normal, p);
    follow_step(s, r, BRT_STEP_TRIANGLES, r->key.id, r->hit.t);
}

/* Layer 3, exact proxies (exact_proxies; analysis, not a way to trace):
** the batching point's triangles answer the proxy test exactly, every
** BVH read once at the start outside the cache and its counts
** (exact_load).  It gives the bound no voxel proxy can beat: make
** figures prints both (Fig. 3: voxel proxies, exact ones in brackets). */
static int exact_proxy_hit(const scheduler *s, uint32_t id, const brt_ray *ray, float tlimit)
{
    brt_ray segment = *ray;
    brt_hit hit;
    segment.tfar = tlimit;
    brt_hit_clear(&hit);
    intersect_ray(&s->exact[id], &segment, BRT_TAG_OCCLUSION, &hit, NULL, NULL);
    return hit.t == 0.0f;
}

/* The paper's proxy question: may the ray hit batching point id's
** triangles in [tnear, tlimit]?  *t (when not NULL): where the proxy
** cast met its first set voxel.  schedule_reference asks it too. */
/* A point of instances' proxy is dilated by INSTANCE_DILATION of a voxel
** (instance points), which covers the rounding of the ray's transform
** while the ray's margin does not exceed it; a ray from farther away (a
** larger margin) is admitted untested. */
static int proxy_cast(const brt_scene *scene, uint32_t id, const brt_ray *ray, float tlimit, float *t)
{
    const batch_entry *b = &scene->batches[id];
    if (b->instances && !(margin_of(&b->margin, ray) <= INSTANCE_DILATION * b->proxy.cell)) {
        if (t) *t = ray->tnear;
        return 1;
    }
    return brt_proxy_raycast(scene->dag, &b->proxy, ray, ray->tnear, tlimit, t);
}

/* The same question, or layer 3's exact answer (*t: tnear then). */
static int proxy_admits(const scheduler *s, uint32_t id, const brt_ray *ray, float tlimit, float *t)
{
    if (s->exact) {
        if (t) *t = ray->tnear;
        return exact_proxy_hit(s, id, ray, tlimit);
    }
    return proxy_cast(s->scene, id, ray, tlimit, t);
}

/* The paper's proxy test at the batching point where the walk stands: a
** miss culls the visit (no queue, no load).  With proxies off (no_proxy,
** or layer 2) every batching point reached is queued, as in Pharr et al. */
static int proxy_test(const scheduler *s, walker *w, ray_slot *r, float tlimit)
{
    float t = r->key.t;
    int hit;
    if (!s->use_proxies) return 1;
    w->proxy_tests++;
    hit = proxy_admits(s, r->key.id, &r->ray, tlimit, s->follow ? &t : NULL);
    w->proxy_culled += !hit;
    follow_step(s, r, hit ? BRT_STEP_PROXY_HIT : BRT_STEP_PROXY_MISS, r->key.id, t);
    return hit;
}

/* A resident batching point was just used: the LRU order hears of it. */
static void walker_used(walker *w, uint32_t id)
{
    if (w->cache) cache_touch(w->cache, id);
    else use_log_record(w->uses, id);                       /* layer 5 */
}

/* Layer 1, intersecting at once in memory: at a batching point whose
** geometry is resident (and unless paper_scheduler asks for the paper's
** plain scheduler) the ray needs no queue: it is intersected there at
** once and walks on.  Its proxy is not consulted: the BVH answers exactly
** at about the cost of a proxy cast.  Why it matters: a bounce ray starts
** inside the batching point just processed, still in memory; queued, it
** would wait there until that point might be evicted and read again.
** make figures writes the loads and disk bytes with and without it
** (fig3.csv: the paper's scheduler, --paper-scheduler, beside batchrt's).
** Returns 0 when the point is not resident. */
static int intersect_resident(const scheduler *s, walker *w, ray_slot *r, const prepared_ray *p)
{
    const geometry *resident = s->paper_scheduler ? NULL : cache_peek(&s->cache, r->key.id);
    if (!resident) return 0;
    walker_used(w, r->key.id);
    follow_step(s, r, BRT_STEP_RESIDENT, r->key.id, r->key.t);
    r->visits++;
    w->resident_visits++;
    intersect_slot(s, resident, r, p);
    return 1;
}

/* Layer 7, inner proxies: the inner proxy test, first at every batching
** point an occlusion ray with tfar = +inf reaches: a hit settles the ray
** occluded (the record of intersect_slot) with no queue and no load.
** make bench-inner prints how many rays it settles and the disk bytes
** read with and without it. */
static int inner_stops(const scheduler *s, ray_slot *r)
{
    if (!s->use_inner || !is_occlusion(r)) return 0;   /* the cast refuses tfar < inf */
    if (!brt_inner_occludes(s->scene->dag, &s->scene->batches[r->key.id].inner, &r->ray)) return 0;
    hit_mark_occluded(&r->hit);
    follow_step(s, r, BRT_STEP_INNER, r->key.id, r->key.t);
    return 1;
}

/* Continues a ray's top-level walk: stops at the next batching point it
** enters before its closest hit and whose proxy it hits (returned: the
** ray is to be queued there), or finishes (NO_ENTRY).  tlimit is the
** closest hit (a box entered exactly there may still hold an equal-t hit
** with a lower prim, so the compare is inclusive).  An occlusion ray
** also finishes at its first hit.  Writes only the ray's slot and the
** walker w: threads walk different rays at once. */
static uint32_t walk_on(const scheduler *s, walker *w, ray_slot *r)
{
    prepared_ray p;
    /* Boxes grown by the margin of instances (0 without: bvh.c), and
    ** without one the preparation serves the points' BVHs too. */
    const float margin = margin_of(&s->scene->header.margin, &r->ray);
    float tlimit;
    brt_ray_prepare_margin(&r->ray, margin, &p.prep);
    if (!p.prep.valid) return NO_ENTRY;
    brt_box_lanes_of(&p.prep, &p.lanes);
    tlimit = walk_limit(r);
    top_walk_start(&w->walk);
    while (!found_occluder(r) &&
           top_walk_next(&w->walk, s->scene->top, &p.lanes, p.prep.tnear, tlimit, &r->key)) {
        follow_step(s, r, BRT_STEP_ENTER, r->key.id, r->key.t);
        if (inner_stops(s, r)) {                            /* layer 7 */
            w->inner_stopped++;
            break;
        }
        if (intersect_resident(s, w, r, margin == 0.0f ? &p : NULL)) {   /* layer 1 */
            tlimit = walk_limit(r);
            continue;
        }
        if (!proxy_test(s, w, r, tlimit)) continue;
        r->visits++;
        return r->key.id;
    }
    return NO_ENTRY;
}

/* Queues slot's ray at batching point id.  Invariant (make debug): the
** ray's walk stopped there because the proxy admits it. */
static brt_result enqueue(scheduler *s, uint32_t id, uint32_t slot)
{
    ray_queue *q = &s->queues[id];
    assert(!s->use_proxies ||
           proxy_admits(s, id, &s->slots[slot].ray, walk_limit(&s->slots[slot]), NULL));
    if (q->count == q->capacity) {
        uint32_t *grown = brt_grow(q->slots, &q->capacity, (size_t)q->count + 1, sizeof *grown);
        if (!grown) return BRT_ENOMEM;
        q->slots = grown;
    }
    q->slots[q->count++] = slot;
    heap_lower(&s->fullest, queue_key(q->count, id));
    s->stats->queued_visits++;
    follow_step(s, &s->slots[slot], BRT_STEP_QUEUED, id, s->slots[slot].key.t);
    return BRT_OK;
}

/* ---- layer 8: batching points owned by other processes ---- */

#define ARRIVALS_PER_TAKE 1024u   /* rays taken from the exchange per call */

static int owned_elsewhere(const scheduler *s, uint32_t id)
{
    return s->exchange && s->exchange->foreign[id];
}

/* A ray slot as it travels (brt_ray_state), and back: the whole of a
** waiting ray's state, so its walk resumes where it stopped. */
static void state_of_slot(const ray_slot *r, brt_ray_state *state)
{
    memset(state, 0, sizeof *state);
    state->ray = r->ray;
    state->hit = r->hit;
    memcpy(state->normal, r->normal, sizeof state->normal);
    state->key_t = r->key.t;
    state->key_point = r->key.id;
    state->visits = r->visits;
    state->tag = r->tag;
}

static void slot_of_state(const brt_ray_state *state, ray_slot *r)
{
    r->ray = state->ray;
    r->hit = state->hit;
    memcpy(r->normal, state->normal, sizeof r->normal);
    r->key.t = state->key_t;
    r->key.id = state->key_point;
    r->visits = state->visits;
    r->tag = state->tag;
}

/* Sends slot's ray to the process owning the batching point where its
** walk stopped (its key's); the slot is free again. */
static brt_result forward(scheduler *s, uint32_t slot)
{
    brt_ray_state state;
    state_of_slot(&s->slots[slot], &state);
    s->free_slots[s->free_count++] = slot;
    return s->exchange->send(s->exchange->user, &state) == 0 ? BRT_OK : BRT_EIO;
}

static brt_result settle_failure(brt_result r, brt_error *err);

/* Queues rays sent here by other processes at the points they stopped at
** (their proxies admitted them there): waits for them when idle.  Returns
** how many came; 0 with idle means every process is done. */
static size_t take_rays(scheduler *s, int idle, brt_result *res, brt_error *err)
{
    const uint32_t points = s->scene->header.batch_count;
    size_t max = s->free_count < ARRIVALS_PER_TAKE ? s->free_count : ARRIVALS_PER_TAKE, n, i;
    if (!s->exchange || max == 0) return 0;
    n = s->exchange->receive(s->exchange->user, s->arrivals, max, idle);
    if (n > max) {
        *res = brt_fail(err, BRT_EARG, "ray exchange: receive returned %lu rays for room for %lu",
                        (unsigned long)n, (unsigned long)max);
        return 0;
    }
    for (i = 0; i < n && *res == BRT_OK; i++) {
        const brt_ray_state *a = &s->arrivals[i];
        uint32_t slot;
        if (a->key_point >= points || owned_elsewhere(s, a->key_point)) {
            *res = brt_fail(err, BRT_EFORMAT, "ray exchange: a ray for batching point %lu, not owned here",
                            (unsigned long)a->key_point);
            return 0;
        }
        slot = s->free_slots[--s->free_count];
        slot_of_state(a, &s->slots[slot]);
        if ((*res = enqueue(s, a->key_point, slot)) != BRT_OK) *res = settle_failure(*res, err);
    }
    return n;
}

/* A ray whose walk stopped: queued at batching point id (or sent to the
** process owning it: layer 8), or, when id is NO_ENTRY, finished (the
** source hears of it; its slot is free). */
static brt_result settle(scheduler *s, uint32_t slot, uint32_t id)
{
    ray_slot *r = &s->slots[slot];
    if (id != NO_ENTRY) return owned_elsewhere(s, id) ? forward(s, slot) : enqueue(s, id, slot);
    s->stats->shadow_occluded += found_occluder(r);
    follow_step(s, r, BRT_STEP_FINISHED, NO_ENTRY, r->hit.t);
    s->source->finished(s->source->user, &r->ray, &r->hit, r->normal, r->visits, r->tag);
    s->free_slots[s->free_count++] = slot;
    return BRT_OK;
}

/* A walker's counters go to the statistics. */
static void walker_count(scheduler *s, walker *w)
{
    s->stats->resident_visits += w->resident_visits;
    s->stats->proxy_tests += w->proxy_tests;
    s->stats->proxy_culled += w->proxy_culled;
    s->stats->shadow_inner_stopped += w->inner_stopped;
    w->resident_visits = w->proxy_tests = w->proxy_culled = w->inner_stopped = 0;
}

/* The rays of slots[0..count): first intersected at batching point id
** (its geometry g; id is NO_ENTRY for new rays), then each walks on and is
** settled.
** Releasing the point before the walks makes its place in the LRU order
** come before the points the walks use (no ray of its queue enters it
** again: walk keys only grow).  With threads, layer 5 does the same in
** phases. */
static brt_result run_rays(scheduler *s, const uint32_t *slots, uint32_t count, uint32_t id,
                           const geometry *g)
{
    brt_result r = BRT_OK;
    uint32_t i;
    if (s->threads) return phases_run(s, slots, count, id, g);       /* layer 5 */
    if (id != NO_ENTRY) {
        for (i = 0; i < count; i++) intersect_slot(s, g, &s->slots[slots[i]], NULL);
        cache_release(&s->cache, id);
    }
    for (i = 0; i < count && r == BRT_OK; i++)
        r = settle(s, slots[i], walk_on(s, &s->walker, &s->slots[slots[i]]));
    walker_count(s, &s->walker);
    return r;
}

/* Why settling rays failed: a full memory, or an exchange that could
** not send (layer 8). */
static brt_result settle_failure(brt_result r, brt_error *err)
{
    if (r == BRT_EIO) return brt_fail(err, r, "ray exchange: a ray could not be sent");
    return brt_fail(err, r, "out of memory in the ray queues");
}

/* A new ray in slot r: the miss record, no visit yet, its walk to start
** at the root; counted. */
static void slot_start(ray_slot *r, const brt_ray *ray, uint64_t tag, brt_stats *stats)
{
    r->ray = *ray;
    r->tag = tag;
    brt_hit_clear(&r->hit);
    r->normal[0] = r->normal[1] = r->normal[2] = 0.0f;
    r->visits = 0;
    r->key.t = -INFINITY;
    r->key.id = TOP_EMPTY;
    stats->rays++;
    stats->shadow_rays += is_occlusion(r);
}

/* Takes the rays other processes sent (layer 8), then new rays from the
** source while there are free slots; each new ray walks from the root. */
static brt_result refill(scheduler *s, brt_error *err)
{
    brt_result taken = BRT_OK;
    take_rays(s, 0, &taken, err);
    if (taken != BRT_OK) return taken;
    while (s->free_count > 0) {
        size_t n = s->source->next_rays(s->source->user, s->incoming, s->incoming_tags, s->free_count), i;
        brt_result res;
        if (n == 0) return BRT_OK;
        if (n > s->free_count)      /* it may have written past the room it was given */
            return brt_fail(err, BRT_EARG, "ray source: next_rays returned %lu rays for room for %lu",
                            (unsigned long)n, (unsigned long)s->free_count);
        for (i = 0; i < n; i++) {
            s->fresh[i] = s->free_slots[--s->free_count];
            slot_start(&s->slots[s->fresh[i]], &s->incoming[i], s->incoming_tags[i], s->stats);
        }
        res = run_rays(s, s->fresh, (uint32_t)n, NO_ENTRY, NULL);
        if (res != BRT_OK) return settle_failure(res, err);
    }
    return BRT_OK;
}

/* Nonzero when every ray of the queue is an occlusion ray. */
static int only_occlusion(const scheduler *s, const ray_queue *q)
{
    uint32_t i;
    for (i = 0; i < q->count; i++)
        if (!is_occlusion(&s->slots[q->slots[i]])) return 0;
    return 1;
}

/* Fetches batching point id for its queue (cache_fetch: the paper's LRU
** geometry cache), and, layer 6 (statistics only), books the load, if
** there is one, as the shadow rays' when they alone asked for it. */
static brt_result fetch_for(scheduler *s, uint32_t id, const ray_queue *q, const geometry **g,
                            brt_error *err)
{
    uint64_t loads = s->stats->batch_loads, bytes = s->stats->disk_bytes_read;
    brt_result r = cache_fetch(&s->cache, id, g, err);
    s->fetch_bytes = s->stats->disk_bytes_read - bytes;
    if (r == BRT_OK && s->stats->batch_loads != loads && only_occlusion(s, q)) {
        s->stats->shadow_batch_loads += s->stats->batch_loads - loads;
        s->stats->shadow_disk_bytes_read += s->fetch_bytes;
    }
    return r;
}

/* Intersects every ray queued at batching point id, then moves each on. */
static brt_result process_batch(scheduler *s, uint32_t id, brt_error *err)
{
    ray_queue q = s->queues[id];
    const geometry *g;
    uint32_t i;
    brt_result r = fetch_for(s, id, &q, &g, err);
    if (r != BRT_OK) return r;
    for (i = 0; i < q.count; i++) follow_step(s, &s->slots[q.slots[i]], BRT_STEP_LOAD, id, 0.0f);
    /* Take the queue out first: no ray is queued here again (keys only
    ** grow), but the walks queue rays elsewhere. */
    memset(&s->queues[id], 0, sizeof s->queues[id]);
    r = run_rays(s, q.slots, q.count, id, g);
    free(q.slots);
    return r == BRT_OK ? BRT_OK : settle_failure(r, err);
}

/* Whether the caller asked the trace to stop (brt_trace_options.interrupt). */
static int interrupted(const scheduler *s)
{
    return s->interrupt && *s->interrupt;
}

/* Whether a queue waits.  When none does, other processes may still send
** rays here: wait for them (layer 8; at once false without an exchange). */
static int queues_waiting(scheduler *s, brt_result *r, brt_error *err)
{
    if (s->fullest.size == 0) take_rays(s, 1, r, err);
    return *r == BRT_OK && s->fullest.size > 0;
}

/* The scheduler's loop: the fullest queue first, until every ray is
** finished; new rays whenever slots are free. */
static brt_result schedule(scheduler *s, brt_error *err)
{
    brt_result r = refill(s, err);
    while (r == BRT_OK && queues_waiting(s, &r, err)) {
        if (interrupted(s)) return brt_fail(err, BRT_EINTR, "%s: trace interrupted", s->scene->path);
        r = process_batch(s, (uint32_t)heap_pop(&s->fullest), err);
        if (r == BRT_OK) r = refill(s, err);
    }
    return r == BRT_OK ? cache_check(&s->cache, err) : r;
}

/* Layer 2, proxies off when everything fits: proxies only spare loads.
** When the budget (what is left of it after the proxies) holds every
** blob nothing is ever evicted, so a load a proxy spares is only put off
** -- unless no ray ever needs that batching point -- while every test
** costs a cast.  So the default scheduler does not consult them then;
** the paper's (paper_scheduler) does, and so does a trace over several
** processes (layer 8), where a proxy miss also spares a message.
** render --compare without a limit prints the run's time with and
** without them.  Every blob: the batching points' and the prototypes',
** as the cache charges them (its all_bytes). */
static int proxies_pay(const scheduler *s, uint64_t budget)
{
    return s->paper_scheduler || s->exchange || budget < s->cache.all_bytes;
}

/* Layer 10, few rays in flight in core.  Rays in flight are there to
** gather rays at a batching point before its load.  When the budget holds
** every blob no point is ever loaded twice, so gathering spares no load,
** while a million waiting rays (a ray_slot each) push each other and the
** BVHs out of the processor's caches.  The default is then IN_CORE_RAYS
** (make bench-embree's batched column runs with it; trace --batched
** --rays-in-flight N --stats on the same rays times any other number).
** Not with an exchange (layer 8), whose messages the waiting rays fill. */
#define IN_CORE_RAYS 4096u
#define OUT_OF_CORE_RAYS (1u << 20)

static uint32_t rays_in_flight(const brt_trace_options *opt, uint64_t budget, uint64_t every_blob)
{
    if (opt && opt->rays_in_flight) return opt->rays_in_flight;
    if (!(opt && opt->exchange) && budget >= every_blob) return IN_CORE_RAYS;
    return OUT_OF_CORE_RAYS;
}

/* capacity_hint: the number of rays there will be, when known (0: not),
** so that 20 rays do not get a million slots. */
static brt_result scheduler_init(scheduler *s, brt_scene *scene, const brt_trace_options *opt,
                                 const brt_ray_source *source, size_t capacity_hint,
                                 brt_stats *stats)
{
    uint32_t n = scene->header.batch_count, i;
    uint64_t budget = opt && opt->memory_limit ? opt->memory_limit : UINT64_MAX;
    memset(s, 0, sizeof *s);
    s->scene = scene;
    s->source = source;
    s->stats = stats;
    s->use_proxies = !(opt && opt->no_proxy);
    s->paper_scheduler = opt && opt->paper_scheduler;
    s->use_inner = !(opt && opt->no_inner);
    s->follow = opt && opt->follow ? opt : NULL;
    s->interrupt = opt ? opt->interrupt : NULL;
    s->exchange = opt ? opt->exchange : NULL;
    /* With proxies on, they take their bytes from the same budget (the
    ** paper's Fig. 3 lowers the geometry limit by the proxies' memory). */
    stats->proxy_bytes = s->use_proxies ? brt_svdag_memory_bytes(scene->dag) : 0;
    if (budget != UINT64_MAX) budget = budget > stats->proxy_bytes ? budget - stats->proxy_bytes : 0;
    if (cache_init(&s->cache, scene, budget, opt, stats) != BRT_OK) return BRT_ENOMEM;
    if (!proxies_pay(s, budget)) s->use_proxies = 0;            /* layer 2 */
    s->capacity = rays_in_flight(opt, budget, s->cache.all_bytes);   /* layer 10 */
    if (capacity_hint > 0 && capacity_hint < s->capacity) s->capacity = (uint32_t)capacity_hint;
    stats->memory_limit = opt ? opt->memory_limit : 0;
    stats->batching_points = n;
    stats->geometry_bytes = scene->header.geometry_bytes;
    s->slots = malloc((size_t)s->capacity * sizeof *s->slots);
    s->free_slots = malloc((size_t)s->capacity * sizeof *s->free_slots);
    s->queues = calloc(n, sizeof *s->queues);
    s->fullest.keys = malloc((size_t)n * sizeof *s->fullest.keys);
    s->fullest.pos = malloc((size_t)n * sizeof *s->fullest.pos);
    s->incoming = malloc((size_t)s->capacity * sizeof *s->incoming);
    s->incoming_tags = malloc((size_t)s->capacity * sizeof *s->incoming_tags);
    s->fresh = malloc((size_t)s->capacity * sizeof *s->fresh);
    s->walker.walk.keys = malloc(((size_t)n + scene->header.top_node_count) * sizeof *s->walker.walk.keys);
    s->walker.cache = &s->cache;
    if (!s->slots || !s->free_slots || !s->queues || !s->fullest.keys || !s->fullest.pos || !s->incoming ||
        !s->incoming_tags || !s->fresh || !s->walker.walk.keys ||
        (s->exchange && !(s->arrivals = malloc(ARRIVALS_PER_TAKE * sizeof *s->arrivals))) ||
        threads_init(s, opt ? opt->threads : 0) != BRT_OK)
        return BRT_ENOMEM;
    for (i = 0; i < n; i++) s->fullest.pos[i] = HEAP_ABSENT;
    for (i = 0; i < s->capacity; i++) s->free_slots[i] = s->capacity - 1 - i;
    s->free_count = s->capacity;
    return BRT_OK;
}

static void scheduler_free(scheduler *s)
{
    uint32_t i;
    threads_free(s);
    for (i = 0; s->queues && i < s->scene->header.batch_count; i++) free(s->queues[i].slots);
    cache_free(&s->cache);
    free(s->slots);
    free(s->free_slots);
    free(s->queues);
    free(s->fullest.keys);
    free(s->fullest.pos);
    free(s->incoming);
    free(s->incoming_tags);
    free(s->fresh);
    free(s->walker.walk.keys);
    free(s->arrivals);
    for (i = 0; s->exact_views && i < s->cache.entry_count; i++) {
        view_free(&s->exact_views[i]);
        blob_free(s->scene, i, s->exact_data[i]);
    }
    free(s->exact);
    free(s->exact_views);
    free(s->exact_data);
    free(s->exact_prototypes);
}

/* Layer 3's set-up (exact_proxies): every batching point's BVH, read
** once, outside the cache and its statistics (exact_proxy_hit). */
static brt_result exact_load(scheduler *s, brt_error *err)
{
    const uint32_t b = s->scene->header.batch_count, n = s->cache.entry_count;
    uint64_t uncounted = 0;
    uint32_t i;
    brt_result r = BRT_OK;
    s->exact = calloc(b, sizeof *s->exact);
    s->exact_views = calloc(n, sizeof *s->exact_views);
    s->exact_data = calloc(n, sizeof *s->exact_data);
    s->exact_prototypes = calloc((size_t)n - b + 1, sizeof *s->exact_prototypes);
    if (!s->exact || !s->exact_views || !s->exact_data || !s->exact_prototypes)
        return brt_fail(err, BRT_ENOMEM, "out of memory for the exact proxies");
    for (i = 0; i < n && r == BRT_OK; i++)
        r = blob_read(&s->cache, i, &uncounted, &s->exact_data[i], &s->exact_views[i], err);
    for (i = b; i < n; i++) s->exact_prototypes[i - b] = s->exact_views[i].bvh;
    for (i = 0; i < b; i++) {
        s->exact[i].triangles = s->exact_views[i].bvh;
        s->exact[i].instances = s->exact_views[i].set;
        s->exact[i].prototypes = s->exact_prototypes;
    }
    return r;
}

/* ---- the paper's loop, plain (schedule_reference) --------------------- */
/*
** The loop of this section with every layer off -- one thread,
** paper_scheduler, no_inner, no_decode, no exchange -- as one function
** to be read top to bottom, as pbrt-v4's BVHAggregate::Intersect reads:
** rays walk the top-level BVH; at each batching point whose proxy admits
** a ray (cast up to its closest hit so far) the ray is queued and stops;
** when no ray can move, the fullest queue is served -- its blob (and a
** point of instances' prototypes) pinned in the LRU geometry cache, its
** rays intersected, the blobs released -- and each of its rays walks on
** from where it stopped; until every ray has finished.  It shares only
** the plain parts: the top-level walk, proxy_cast, blob_read,
** intersect_ray, and geometry_cache as a table of blobs (not cache_fetch,
** whose read-ahead and decoding are layers).  Why it is here: the layered
** loop spreads the same decisions over a dozen functions with a hook
** each; the "reference:" tests hold this one's loads, hits, finished
** order and counts equal to the layered loop's with its layers off, so
** each layer stays a named departure from it.  brt_trace_options.reference
** runs it.  Its LRU order is each blob's last release (released[]), the
** order the layered cache's list keeps.
*/

/* Pins blob id (a batching point's or a prototype's): when it is not
** resident, evicts the least recently released unpinned blobs until it
** fits the budget (or none is left: a blob larger than the budget is
** then held alone), and loads it. */
static brt_result reference_pin(geometry_cache *c, uint64_t *released, uint32_t id, brt_error *err)
{
    const uint32_t points = c->scene->header.batch_count;
    const uint64_t bytes = cache_bytes(c->scene, id);
    cache_entry *e = &c->entries[id];
    brt_result r;
    e->pins = 1;
    while (!e->data && c->held + bytes > c->budget) {
        uint32_t old = NO_ENTRY, k;
        for (k = 0; k < c->entry_count; k++)
            if (c->entries[k].data && c->entries[k].pins == 0 &&
                (old == NO_ENTRY || released[k] < released[old]))
                old = k;
        if (old == NO_ENTRY) break;
        c->held -= c->entries[old].bytes;
        view_free(&c->entries[old].view);
        blob_free(c->scene, old, c->entries[old].data);
        c->entries[old].data = NULL;
        if (old >= points) c->prototypes[old - points] = NULL;
    }
    if (e->data) return BRT_OK;
    if ((r = blob_read(c, id, &c->stats->disk_bytes_read, &e->data, &e->view, err)) != BRT_OK) return r;
    e->geometry.triangles = e->view.bvh;
    e->geometry.instances = e->view.set;
    e->geometry.prototypes = c->prototypes;
    if (id >= points) c->prototypes[id - points] = e->view.bvh;
    e->bytes = bytes;
    c->held += bytes;
    if (id < points) c->stats->batch_loads++;
    else c->stats->prototype_loads++;
    c->stats->oversized_loads += bytes > c->budget;
    if (c->stats->cache_peak_bytes < c->held) c->stats->cache_peak_bytes = c->held;
    return BRT_OK;
}

/* The paper's loop (above).  Of the options it reads memory_limit,
** no_proxy, rays_in_flight (0: OUT_OF_CORE_RAYS), read_fn, read_user and
** drop_os_cache; the rest are layers and hooks. */
static brt_result schedule_reference(brt_scene *scene, const brt_trace_options *opt,
                                     const brt_ray_source *source, size_t capacity_hint,
                                     brt_stats *stats, brt_error *err)
{
    const uint32_t points = scene->header.batch_count;
    const int use_proxies = !(opt && opt->no_proxy);
    uint32_t capacity = opt && opt->rays_in_flight ? opt->rays_in_flight : OUT_OF_CORE_RAYS;
    uint64_t budget = UINT64_MAX, clock = 0;
    uint32_t free_count = 0, walking_count = 0, best, i, k;
    geometry_cache c;                           /* the blobs: data, view, pins, bytes */
    top_walk walk;
    ray_slot *slots;
    ray_queue *queues;
    uint32_t *free_slots, *walking;
    uint64_t *released, *tags;
    brt_ray *incoming;
    const instance_set *set;
    size_t n;
    brt_result r = BRT_OK;
    if (capacity_hint > 0 && capacity_hint < capacity) capacity = (uint32_t)capacity_hint;
    /* The proxies' bytes come out of the limit (the paper's Fig. 3). */
    stats->proxy_bytes = use_proxies ? brt_svdag_memory_bytes(scene->dag) : 0;
    if (opt && opt->memory_limit)
        budget = opt->memory_limit > stats->proxy_bytes ? opt->memory_limit - stats->proxy_bytes : 0;
    if (opt) stats->memory_limit = opt->memory_limit;
    stats->batching_points = points;
    stats->geometry_bytes = scene->header.geometry_bytes;
    if (cache_init(&c, scene, budget, opt, stats) != BRT_OK)
        return brt_fail(err, BRT_ENOMEM, "out of memory for the geometry cache");
    slots = malloc((size_t)capacity * sizeof *slots);
    free_slots = malloc((size_t)capacity * sizeof *free_slots);
    walking = malloc((size_t)capacity * sizeof *walking);
    incoming = malloc((size_t)capacity * sizeof *incoming);
    tags = malloc((size_t)capacity * sizeof *tags);
    queues = calloc(points, sizeof *queues);
    released = calloc(c.entry_count, sizeof *released);
    walk.keys = malloc(((size_t)points + scene->header.top_node_count) * sizeof *walk.keys);
    walk.pos = NULL;                            /* a walk lowers no key in place */
    if (!slots || !free_slots || !walking || !incoming || !tags || !queues || !released || !walk.keys)
        r = brt_fail(err, BRT_ENOMEM, "out of memory for %u rays in flight", capacity);
    else
        for (free_count = 0; free_count < capacity; free_count++) free_slots[free_count] = free_count;
    while (r == BRT_OK) {
        /* Each ray of walking walks on from its key, past the batching
        ** points whose proxies prove a miss, to the next one whose proxy
        ** admits it before its closest hit: queued there; or it finishes. */
        for (i = 0; i < walking_count; i++) {
            ray_slot *ray = &slots[walking[i]];
            const float tlimit = walk_limit(ray);
            uint32_t stop = NO_ENTRY;
            brt_ray_prep prep;
            brt_box_lanes lanes;
            brt_ray_prepare_margin(&ray->ray, margin_of(&scene->header.margin, &ray->ray), &prep);
            if (prep.valid && !found_occluder(ray)) {
                brt_box_lanes_of(&prep, &lanes);
                top_walk_start(&walk);
                while (stop == NO_ENTRY &&
                       top_walk_next(&walk, scene->top, &lanes, prep.tnear, tlimit, &ray->key)) {
                    if (use_proxies) {
                        stats->proxy_tests++;
                        if (!proxy_cast(scene, ray->key.id, &ray->ray, tlimit, NULL)) {
                            stats->proxy_culled++;      /* a proven miss: no queue, no load */
                            continue;
                        }
                    }
                    stop = ray->key.id;
                }
            }
            if (stop != NO_ENTRY) {
                ray_queue *q = &queues[stop];
                uint32_t *grown = brt_grow(q->slots, &q->capacity, (size_t)q->count + 1, sizeof *grown);
                if (!grown) {
                    r = brt_fail(err, BRT_ENOMEM, "out of memory in the ray queues");
                    break;
                }
                q->slots = grown;
                q->slots[q->count++] = walking[i];
                ray->visits++;
                stats->queued_visits++;
            } else {
                stats->shadow_occluded += found_occluder(ray);
                source->finished(source->user, &ray->ray, &ray->hit, ray->normal, ray->visits, ray->tag);
                free_slots[free_count++] = walking[i];
            }
        }
        if (r != BRT_OK) break;
        /* New rays into the free slots, while the source has some; each
        ** walks from the root. */
        n = free_count > 0 ? source->next_rays(source->user, incoming, tags, free_count) : 0;
        if (n > free_count) {
            r = brt_fail(err, BRT_EARG, "ray source: next_rays returned %lu rays for room for %lu",
                         (unsigned long)n, (unsigned long)free_count);
            break;
        }
        for (walking_count = 0; walking_count < n; walking_count++) {
            walking[walking_count] = free_slots[--free_count];
            slot_start(&slots[walking[walking_count]], &incoming[walking_count], tags[walking_count], stats);
        }
        if (walking_count > 0) continue;
        /* No ray can move: serve the fullest queue (ties: the lowest id),
        ** so that each load serves as many rays as it can. */
        best = NO_ENTRY;
        for (k = 0; k < points; k++)
            if (queues[k].count > 0 && (best == NO_ENTRY || queues[k].count > queues[best].count)) best = k;
        if (best == NO_ENTRY) break;                        /* every ray has finished */
        /* Its blob and, for a point of instances, each prototype it uses
        ** pinned in memory. */
        r = reference_pin(&c, released, best, err);
        set = c.entries[best].view.set;
        for (k = 0; r == BRT_OK && set && k < set->use_count; k++)
            r = reference_pin(&c, released, points + set->uses[k], err);
        if (r != BRT_OK) break;
        /* Its rays intersected there, the blobs released (now the most
        ** recently used), and the rays walk on; none comes back to this
        ** point (walk keys only grow). */
        walking_count = queues[best].count;
        memcpy(walking, queues[best].slots, (size_t)walking_count * sizeof *walking);
        queues[best].count = 0;
        for (i = 0; i < walking_count; i++) {
            ray_slot *ray = &slots[walking[i]];
            intersect_ray(&c.entries[best].geometry, &ray->ray, ray->tag, &ray->hit, ray->normal, NULL);
        }
        c.entries[best].pins = 0;
        released[best] = ++clock;
        for (k = 0; set && k < set->use_count; k++) {
            c.entries[points + set->uses[k]].pins = 0;
            released[points + set->uses[k]] = ++clock;
        }
    }
    for (k = 0; queues && k < points; k++) free(queues[k].slots);
    cache_free(&c);
    free(slots);
    free(free_slots);
    free(walking);
    free(incoming);
    free(tags);
    free(queues);
    free(released);
    free(walk.keys);
    return r;
}

static brt_result trace_source(brt_scene *scene, const brt_trace_options *opt,
                               const brt_ray_source *source, size_t capacity_hint,
                               brt_stats *stats, brt_error *err)
{
    scheduler s;
    brt_stats local;
    double start = brt_seconds();
    brt_result r;
    if (!stats) stats = &local;
    memset(stats, 0, sizeof *stats);
    if (opt && opt->drop_os_cache) posix_fadvise(scene->fd, 0, 0, POSIX_FADV_DONTNEED);
    if (opt && opt->reference) {
        r = schedule_reference(scene, opt, source, capacity_hint, stats, err);
    } else {
        r = scheduler_init(&s, scene, opt, source, capacity_hint, stats);
        if (r != BRT_OK) r = brt_fail(err, r, "out of memory for %u rays in flight", s.capacity);
        else if (opt && opt->exact_proxies && s.use_proxies) r = exact_load(&s, err);
        if (r == BRT_OK) r = schedule(&s, err);
        scheduler_free(&s);
    }
    stats->visits = stats->queued_visits + stats->resident_visits;
    stats->seconds = brt_seconds() - start;
    if (stats->seconds > 0) stats->mrays_per_second = (double)stats->rays / stats->seconds * 1e-6;
    return r;
}

brt_result brt_scene_trace_stream(brt_scene *scene, const brt_trace_options *opt,
                                  const brt_ray_source *source, brt_stats *stats,
                                  brt_error *err)
{
    return trace_source(scene, opt, source, 0, stats, err);
}

/* brt_scene_trace and brt_scene_occluded on top of the stream: rays are
** handed out in order and the tag is the index of the answer to write
** (with BRT_TAG_OCCLUSION when the answers are occlusion bytes). */
typedef struct array_source {
    const brt_ray *rays;
    brt_hit *hits;              /* closest hits, or NULL */
    uint8_t *occluded;          /* or occlusion bytes */
    size_t count, next;
} array_source;

static size_t array_next(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    array_source *a = user;
    size_t n = a->count - a->next < max ? a->count - a->next : max, i;
    for (i = 0; i < n; i++) {
        rays[i] = a->rays[a->next];
        tags[i] = a->next++ | (a->occluded ? BRT_TAG_OCCLUSION : 0);
    }
    return n;
}

static void array_finished(void *user, const brt_ray *ray, const brt_hit *hit,
                           const float normal[3], uint32_t visits, uint64_t tag)
{
    array_source *a = user;
    (void)ray;
    (void)normal;
    (void)visits;
    if (a->occluded) a->occluded[tag & ~BRT_TAG_OCCLUSION] = hit->prim != BRT_NO_PRIM;
    else a->hits[tag] = *hit;
}

static brt_result trace_array(brt_scene *scene, const brt_trace_options *opt, array_source *a,
                              brt_stats *stats, brt_error *err)
{
    brt_ray_source source;
    a->next = 0;
    source.next_rays = array_next;
    source.finished = array_finished;
    source.user = a;
    return trace_source(scene, opt, &source, a->count > 0 ? a->count : 1, stats, err);
}

/* The array forms: either hits or occluded is written (the other NULL). */
static brt_result trace_rays(brt_scene *scene, const brt_trace_options *opt,
                             const brt_ray *rays, size_t count, brt_hit *hits,
                             uint8_t *occluded, brt_stats *stats, brt_error *err)
{
    array_source a;
    a.rays = rays;
    a.hits = hits;
    a.occluded = occluded;
    a.count = count;
    return trace_array(scene, opt, &a, stats, err);
}

brt_result brt_scene_trace(brt_scene *scene, const brt_trace_options *opt,
                           const brt_ray *rays, size_t count, brt_hit *hits,
                           brt_stats *stats, brt_error *err)
{
    return trace_rays(scene, opt, rays, count, hits, NULL, stats, err);
}

brt_result brt_scene_occluded(brt_scene *scene, const brt_trace_options *opt,
                              const brt_ray *rays, size_t count, uint8_t *occluded,
                              brt_stats *stats, brt_error *err)
{
    return trace_rays(scene, opt, rays, count, NULL, occluded, stats, err);
}

/* ---- owners of batching points (layer 8) ---- */

/* What a load of point id reads: its blob (cache_bytes) and, for a point
** of instances, its triangles' share of the prototypes' bytes -- an
** estimate: which prototypes it uses is in its blob, on disk. */
static double point_weight(const brt_scene *s, uint32_t id)
{
    double bytes = (double)cache_bytes(s, id), proto_bytes = 0.0, proto_tris = 0.0;
    uint32_t i;
    if (!s->batches[id].instances) return bytes;
    for (i = 0; i < s->header.prototype_count; i++) {
        proto_bytes += (double)s->prototypes[i].size;
        proto_tris += (double)s->prototypes[i].triangles;
    }
    return proto_tris > 0.0 ? bytes + (double)s->batches[id].triangles * proto_bytes / proto_tris : bytes;
}

/* The batching points in the top-level BVH's leaf order (depth first,
** lanes in order): neighbours in it are neighbours in space.  stack has
** room for every node and point code. */
static uint32_t top_leaf_order(const brt_scene *s, uint32_t *order, uint32_t *stack)
{
    uint32_t depth = 0, n = 0;
    int lane;
    if (s->header.top_node_count > 0) stack[depth++] = 0;
    while (depth > 0) {
        uint32_t code = stack[--depth];
        if (code & TOP_LEAF) {
            order[n++] = code & ~TOP_LEAF;
            continue;
        }
        for (lane = 3; lane >= 0; lane--)           /* popped in lane order */
            if (s->top[code].child[lane] != TOP_EMPTY) stack[depth++] = s->top[code].child[lane];
    }
    return n;
}

brt_result brt_scene_assign(const brt_scene *scene, uint32_t processes, int round_robin,
                            uint32_t *owner, brt_error *err)
{
    const uint32_t points = scene->header.batch_count;
    uint32_t *order = malloc(((size_t)points + 1) * sizeof *order), n, k;
    uint32_t *stack = malloc(((size_t)points + scene->header.top_node_count + 1) * sizeof *stack);
    double total = 0.0, before = 0.0;
    brt_result r = BRT_OK;
    if (processes == 0) r = brt_fail(err, BRT_EARG, "%s: batching points for 0 processes", scene->path);
    else if (!order || !stack)
        r = brt_fail(err, BRT_ENOMEM, "out of memory for the owners of %lu batching points",
                     (unsigned long)points);
    else {
        n = top_leaf_order(scene, order, stack);
        assert(n == points);   /* check_top: every point is one leaf */
        for (k = 0; k < n; k++) total += point_weight(scene, order[k]);
        /* A run ends where the bytes before a point's middle pass the next
        ** multiple of total / processes. */
        for (k = 0; k < n; k++) {
            double w = point_weight(scene, order[k]);
            uint32_t run = total > 0.0 ? (uint32_t)((before + 0.5 * w) / total * processes) : 0;
            owner[order[k]] = round_robin ? k % processes : (run < processes ? run : processes - 1);
            before += w;
        }
    }
    free(order);
    free(stack);
    return r;
}

/* ---- the geometry cache ---------------------------------------------------- */
/*
** Blobs are read whole, with pread, into page-aligned buffers, in requests
** of at most CACHE_READ_CHUNK bytes.  The budget counts the page-rounded
** bytes held.  A blob larger than the budget is allowed when it is the
** only one held (it is counted in stats->oversized_loads).
**
** Each buffer is its own anonymous mapping (mmap), returned to the system
** by munmap on eviction.  Why not malloc: glibc serves blobs below its
** mmap threshold (which grows once a large block is freed) from the heap
** and keeps freed heap resident, so the peak RSS of a long render would
** exceed the memory bound; with mappings the resident bytes follow what
** the cache holds (make bench-scale checks the bound).
*/
#define CACHE_READ_CHUNK ((size_t)8 << 20)

static void lru_unlink(geometry_cache *c, uint32_t id)
{
    cache_entry *e = &c->entries[id];
    if (e->lru_prev != NO_ENTRY) c->entries[e->lru_prev].lru_next = e->lru_next;
    else c->lru_head = e->lru_next;
    if (e->lru_next != NO_ENTRY) c->entries[e->lru_next].lru_prev = e->lru_prev;
    else c->lru_tail = e->lru_prev;
    e->lru_prev = e->lru_next = NO_ENTRY;
}

static void lru_append(geometry_cache *c, uint32_t id)
{
    cache_entry *e = &c->entries[id];
    e->lru_prev = c->lru_tail;
    e->lru_next = NO_ENTRY;
    if (c->lru_tail != NO_ENTRY) c->entries[c->lru_tail].lru_next = id;
    else c->lru_head = id;
    c->lru_tail = id;
}

/* The bytes of blob id's buffer: its page-rounded size, at least a page. */
static size_t blob_buffer_bytes(const brt_scene *scene, uint32_t id)
{
    uint64_t bytes = round_up_page(scene->blobs[id].size);
    return bytes ? (size_t)bytes : SCENE_PAGE;
}

static void blob_free(const brt_scene *scene, uint32_t id, void *data)
{
    if (data) munmap(data, blob_buffer_bytes(scene, id));
}

/* What blob id costs the budget: its page-rounded buffer, and for a point
** of instances what instance_table_open allocates beside it, bounded from
** its table entry (a frame, two numbers and at most one tree node per
** instance, a prototype number per distinct prototype), so that the limit
** bounds the resident bytes. */
static uint64_t cache_bytes(const brt_scene *scene, uint32_t id)
{
    uint64_t bytes = round_up_page(scene->blobs[id].size);
    if (id < scene->header.batch_count && scene->batches[id].instances)
        bytes += (uint64_t)scene->batches[id].instances *
                 (sizeof(brt_instance_frame) + 3 * sizeof(uint32_t) + sizeof(top_node));
    return bytes;
}

/* What the cache would hold with every blob in memory at once. */
static uint64_t all_cache_bytes(const brt_scene *scene)
{
    const uint32_t n = scene->header.batch_count + scene->header.prototype_count;
    uint64_t bytes = 0;
    uint32_t i;
    for (i = 0; i < n; i++) bytes += cache_bytes(scene, i);
    return bytes;
}

static void view_free(blob_view *view)
{
    brt_bvh_free(view->bvh);
    if (view->set) set_free(view->set);
    free(view->set);
    view->bvh = NULL;
    view->set = NULL;
}

/* Entry id's blob is a prototype's: its BVH leaves or joins the table. */
static void cache_note_prototype(geometry_cache *c, uint32_t id)
{
    const uint32_t b = c->scene->header.batch_count;
    if (id >= b) c->prototypes[id - b] = c->entries[id].view.bvh;
}

static void cache_evict(geometry_cache *c, uint32_t id)
{
    cache_entry *e = &c->entries[id];
    lru_unlink(c, id);
    view_free(&e->view);
    cache_note_prototype(c, id);
    blob_free(c->scene, id, e->data);
    c->held -= e->bytes;
    c->decoded -= e->decoded;
    e->data = NULL;
    e->bytes = e->decoded = 0;
}

static brt_result cache_init(geometry_cache *c, brt_scene *scene, uint64_t budget,
                             const brt_trace_options *opt, brt_stats *stats)
{
    uint32_t i, n = scene->header.batch_count + scene->header.prototype_count;
    memset(c, 0, sizeof *c);
    c->entries = calloc(n, sizeof *c->entries);
    c->prototypes = calloc((size_t)scene->header.prototype_count + 1, sizeof *c->prototypes);
    if (!c->entries || !c->prototypes) {   /* freed here; cache_free after it is harmless */
        free(c->entries);
        free(c->prototypes);
        c->entries = NULL;
        c->prototypes = NULL;
        return BRT_ENOMEM;
    }
    for (i = 0; i < n; i++) c->entries[i].lru_prev = c->entries[i].lru_next = NO_ENTRY;
    c->entry_count = n;
    c->scene = scene;
    c->budget = budget;
    c->lru_head = c->lru_tail = NO_ENTRY;
    c->ahead_id = NO_ENTRY;
    c->read_fn = opt && opt->read_fn ? opt->read_fn : pread_reader;
    c->read_user = opt ? opt->read_user : NULL;
    c->drop_os_cache = opt && opt->drop_os_cache;
    c->decode = !(opt && opt->no_decode);
    c->all_bytes = all_cache_bytes(scene);
    c->stats = stats;
    return BRT_OK;
}

static void cache_ahead_drop(geometry_cache *c);

static void cache_free(geometry_cache *c)
{
    uint32_t i;
    cache_ahead_drop(c);
    for (i = 0; c->entries && i < c->entry_count; i++) {
        view_free(&c->entries[i].view);
        blob_free(c->scene, i, c->entries[i].data);
    }
    free(c->entries);
    free(c->prototypes);
}

/* The cache's own sanity check (SQLite's pcache has one too): the held
** bytes add up, only resident entries are pinned, the LRU list holds
** exactly the unpinned resident entries, and the budget holds unless what
** the last fetch needed alone is larger (one blob; a point of instances
** and its prototypes).  At the end of every trace, and after every fetch
** and release in make debug. */
static brt_result cache_check(const geometry_cache *c, brt_error *err)
{
    uint64_t held = 0, resident = 0, listed = 0, stray_pins = 0;
    uint32_t i, id;
    for (i = 0; i < c->entry_count; i++) {
        const cache_entry *e = &c->entries[i];
        held += e->bytes;
        resident += e->data != NULL;
        listed += e->data && e->pins == 0;
        stray_pins += !e->data && e->pins;
    }
    for (id = c->lru_head; id != NO_ENTRY; id = c->entries[id].lru_next) {
        if (!c->entries[id].data || c->entries[id].pins) break;
        listed--;
    }
    if (held != c->held || listed != 0 || stray_pins != 0)
        return brt_fail(err, BRT_ECHECK, "geometry cache: bookkeeping broken");
    if (held > c->budget && resident > (c->working_set > 1 ? c->working_set : 1))
        return brt_fail(err, BRT_ECHECK, "geometry cache: holds %llu bytes over a budget of %llu",
                        (unsigned long long)held, (unsigned long long)c->budget);
    return BRT_OK;
}

/* Opens blob id, validated: a batching point's BVH by brt_bvh_blob_open
** against the scene's triangle count, holding as many triangles as its
** table entry says (the entries add up to the header's count,
** check_batches); a point of instances' table by instance_table_open; a
** prototype's BVH against its own triangle count. */
static brt_result check_blob(const brt_scene *s, uint32_t id, const void *data, blob_view *view,
                             brt_error *err)
{
    const uint32_t b = s->header.batch_count;
    const uint32_t expect = id < b ? s->batches[id].triangles : s->prototypes[id - b].triangles;
    brt_error why;
    uint32_t held;
    view->bvh = NULL;
    view->set = NULL;
    if (id < b && s->batches[id].instances)
        return instance_table_open(s, id, data, s->blobs[id].size, &view->set, err);
    if (brt_bvh_blob_open(data, s->blobs[id].size, id < b ? s->header.triangle_count : expect,
                          &view->bvh, &why) != BRT_OK)
        return brt_fail(err, BRT_EFORMAT, "%s: %s %u: %s", s->path,
                        id < b ? "batching point" : "prototype", id < b ? id : id - b, why.message);
    held = brt_bvh_triangle_count(view->bvh);
    if (held == expect) return BRT_OK;
    view_free(view);
    return brt_fail(err, BRT_EFORMAT, "%s: %s %u: blob holds %u triangles, its table says %u",
                    s->path, id < b ? "batching point" : "prototype", id < b ? id : id - b, held,
                    expect);
}

/* Reads blob id whole (its page-rounded size, into a mapping of its own,
** bytes read added to *bytes_read), checks its checksum and opens it
** (check_blob); *data is to be freed (blob_free) after the view. */
static brt_result blob_read(const geometry_cache *c, uint32_t id, uint64_t *bytes_read, void **data,
                            blob_view *view, brt_error *err)
{
    const blob_place *b = &c->scene->blobs[id];
    uint64_t bytes = round_up_page(b->size), done = 0;
    brt_result r = BRT_OK;
    view->bvh = NULL;
    view->set = NULL;
    *data = mmap(NULL, blob_buffer_bytes(c->scene, id), PROT_READ | PROT_WRITE,
                 MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (*data == MAP_FAILED) {
        *data = NULL;
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory for blob %u", c->scene->path, id);
    }
    while (done < bytes && r == BRT_OK) {
        size_t chunk = bytes - done < CACHE_READ_CHUNK ? (size_t)(bytes - done) : CACHE_READ_CHUNK;
        r = read_fully(c->scene->fd, (unsigned char *)*data + done, chunk, b->offset + done,
                       c->read_fn, c->read_user, bytes_read, c->scene->path, err);
        done += chunk;
    }
    if (c->drop_os_cache) posix_fadvise(c->scene->fd, (off_t)b->offset, (off_t)bytes, POSIX_FADV_DONTNEED);
    if (r == BRT_OK && brt_checksum64(*data, b->size) != b->checksum)
        r = brt_fail(err, BRT_EFORMAT, "%s: %s %u: checksum mismatch (corrupt file)", c->scene->path,
                     id < c->scene->header.batch_count ? "batching point" : "prototype",
                     id < c->scene->header.batch_count ? id : id - c->scene->header.batch_count);
    if (r == BRT_OK) r = check_blob(c->scene, id, *data, view, err);
    if (r != BRT_OK) {
        blob_free(c->scene, id, *data);
        *data = NULL;
    }
    return r;
}

/* ---- read-ahead ---- */
/*
** While the threads intersect the rays of one batching point, a thread of
** the cache's own reads the blob of the fullest queue left (the likely
** next load: cache_read_ahead).  The schedule does not change: when the
** scheduler then asks for that blob, cache_load takes the buffer read
** ahead instead of reading (the same bytes, counted then, as a load of
** the same size would be).  When it asks for another blob first, the
** buffer is kept for later: the guess is most often late, not wrong (a
** point whose queue was fullest is served a few batches on), and reading
** it again would spend the disk twice.  It is dropped uncounted when a
** new guess replaces it.  So every count is the one-thread count, and
** only the wall time differs.  The buffer, running or kept, is held
** beside the budget: one blob more at most (README, "Threads").  read_fn
** is never called by two threads at once: a running read-ahead is joined
** before any other read.  (A point of instances' prototypes are not read
** ahead.)
*/
static void *ahead_main(void *arg)
{
    geometry_cache *c = arg;
    double start = brt_seconds();
    c->ahead_result = blob_read(c, c->ahead_id, &c->ahead_bytes, &c->ahead_data, &c->ahead_view, NULL);
    c->ahead_seconds = brt_seconds() - start;
    return NULL;
}

/* Waits for a running read-ahead; a failed one leaves no buffer (the
** scheduler's own read will meet the failure, and report it). */
static void cache_ahead_join(geometry_cache *c)
{
    if (!c->ahead_running) return;
    pthread_join(c->ahead_thread, NULL);
    c->ahead_running = 0;
    if (c->ahead_result != BRT_OK) c->ahead_id = NO_ENTRY;   /* blob_read freed its buffer */
}

/* Drops the buffer read ahead, if any, uncounted. */
static void cache_ahead_drop(geometry_cache *c)
{
    cache_ahead_join(c);
    if (c->ahead_id == NO_ENTRY) return;
    view_free(&c->ahead_view);
    blob_free(c->scene, c->ahead_id, c->ahead_data);
    c->ahead_id = NO_ENTRY;
}

/* Starts reading blob id ahead, unless it is in memory, already read
** ahead, or a read-ahead is under way; a kept buffer of another blob is
** dropped for it. */
static void cache_read_ahead(geometry_cache *c, uint32_t id)
{
    if (!c->read_ahead || id == NO_ENTRY || c->ahead_running || c->entries[id].data || c->ahead_id == id)
        return;
    cache_ahead_drop(c);
    c->ahead_id = id;
    c->ahead_bytes = 0;
    c->ahead_data = NULL;
    c->ahead_view.bvh = NULL;
    c->ahead_view.set = NULL;
    c->ahead_running = pthread_create(&c->ahead_thread, NULL, ahead_main, c) == 0;
    if (!c->ahead_running) c->ahead_id = NO_ENTRY;
}

/* 1 when blob id was read ahead without error: its buffer and view are
** then the caller's.  Else 0, with any running read-ahead joined, so
** that the caller may read. */
static int cache_ahead_take(geometry_cache *c, uint32_t id)
{
    cache_ahead_join(c);
    if (c->ahead_id != id) return 0;
    c->ahead_id = NO_ENTRY;
    return 1;
}

/* Layer 9, decoded points in core: a BVH blob just loaded is decoded to
** bvh.c's resident layout (brt_bvh_decode: float boxes and blocks of four
** triangles, the same hits bit for bit) when the budget holds its bytes
** beside every blob of the scene and the layouts decoded so far.  Why:
** the quantized walk decodes every node it visits, several times the cost
** of the box test (make bench-embree: batched with and without), while
** the layout takes several times a blob's bytes (make bench-embree
** prints both per triangle).  Decoding only into room that every blob
** leaves free means nothing is ever evicted for it: the loads are those
** of the quantized cache, and out of core, where every byte holds blobs,
** no point is decoded.  Returns the bytes added; out of memory, the point
** stays quantized (as exact, only slower). */
static uint64_t cache_decode(geometry_cache *c, cache_entry *e)
{
    uint64_t bytes;
    if (!c->decode || !e->view.bvh || c->budget < c->all_bytes) return 0;
    bytes = brt_bvh_decoded_bytes(e->view.bvh);
    if (bytes > c->budget - c->all_bytes - c->decoded || brt_bvh_decode(e->view.bvh) != BRT_OK)
        return 0;
    c->decoded += bytes;
    c->stats->decoded_bytes += bytes;
    return bytes;
}

/* Loads blob id into the cache (the caller has made room). */
static brt_result cache_load(geometry_cache *c, uint32_t id, brt_error *err)
{
    cache_entry *e = &c->entries[id];
    uint64_t bytes = cache_bytes(c->scene, id);
    double start = brt_seconds();
    brt_result r = BRT_OK;
    if (cache_ahead_take(c, id)) {
        e->data = c->ahead_data;
        e->view = c->ahead_view;
        c->stats->disk_bytes_read += c->ahead_bytes;
        c->stats->load_seconds += c->ahead_seconds;
        start = brt_seconds();                  /* the decode is timed below */
    } else {
        r = blob_read(c, id, &c->stats->disk_bytes_read, &e->data, &e->view, err);
    }
    if (r != BRT_OK) return r;
    e->decoded = cache_decode(c, e);                        /* layer 9 */
    c->stats->load_seconds += brt_seconds() - start;
    e->geometry.triangles = e->view.bvh;
    e->geometry.instances = e->view.set;
    e->geometry.prototypes = c->prototypes;
    cache_note_prototype(c, id);
    e->bytes = bytes + e->decoded;
    c->held += e->bytes;
    if (id < c->scene->header.batch_count) c->stats->batch_loads++;
    else c->stats->prototype_loads++;
    if (bytes > c->budget) c->stats->oversized_loads++;
    if (c->held > c->stats->cache_peak_bytes) c->stats->cache_peak_bytes = c->held;
    return BRT_OK;
}

/* Pins blob id, resident (evicting least recently used unpinned entries
** to make room). */
static brt_result cache_pin(geometry_cache *c, uint32_t id, brt_error *err)
{
    cache_entry *e = &c->entries[id];
    if (!e->data) {
        uint64_t bytes = cache_bytes(c->scene, id);
        brt_result r;
        while (c->lru_head != NO_ENTRY && c->held + bytes > c->budget) cache_evict(c, c->lru_head);
        r = cache_load(c, id, err);
        if (r != BRT_OK) return r;
    } else if (e->pins == 0) {
        lru_unlink(c, id);
    }
    e->pins++;
    return BRT_OK;
}

/* Fetch pins: makes batching point id resident -- and for a point of
** instances every prototype it uses -- and returns its geometry. */
static brt_result cache_fetch(geometry_cache *c, uint32_t id, const geometry **g, brt_error *err)
{
    const instance_set *set;
    uint32_t k;
    brt_result r = cache_pin(c, id, err);
    if (r != BRT_OK) return r;
    set = c->entries[id].view.set;
    c->working_set = 1 + (set ? set->use_count : 0);
    for (k = 0; set && k < set->use_count; k++) {
        if ((r = cache_pin(c, c->scene->header.batch_count + set->uses[k], err)) != BRT_OK) {
            while (k-- > 0) cache_release_blob(c, c->scene->header.batch_count + set->uses[k]);
            cache_release_blob(c, id);
            return r;
        }
    }
    *g = &c->entries[id].geometry;
    assert(cache_check(c, NULL) == BRT_OK);
    return BRT_OK;
}

/* The geometry of batching point id if it is in memory (with every
** prototype it uses), or NULL.  Never loads and changes nothing, so that
** threads may ask at once; the scheduler reports the use afterwards with
** cache_touch. */
static const geometry *cache_peek(const geometry_cache *c, uint32_t id)
{
    const instance_set *set = c->entries[id].view.set;
    uint32_t k;
    if (!c->entries[id].data) return NULL;
    for (k = 0; set && k < set->use_count; k++)
        if (!c->prototypes[set->uses[k]]) return NULL;
    return &c->entries[id].geometry;
}

static void cache_touch_blob(geometry_cache *c, uint32_t id)
{
    if (c->entries[id].data && c->entries[id].pins == 0) {
        lru_unlink(c, id);
        lru_append(c, id);
    }
}

/* fn on batching point id's blob and, for a point of instances, on each
** prototype it uses: what a touch and a release act on. */
static void for_point_blobs(geometry_cache *c, uint32_t id,
                            void (*fn)(geometry_cache *c, uint32_t blob))
{
    const instance_set *set = c->entries[id].view.set;
    uint32_t k;
    fn(c, id);
    for (k = 0; set && k < set->use_count; k++) fn(c, c->scene->header.batch_count + set->uses[k]);
}

/* Batching point id, resident, counts as just used (its prototypes too). */
static void cache_touch(geometry_cache *c, uint32_t id)
{
    for_point_blobs(c, id, cache_touch_blob);
}

static void cache_release_blob(geometry_cache *c, uint32_t id)
{
    assert(c->entries[id].pins > 0);
    if (--c->entries[id].pins == 0) lru_append(c, id);
}

/* Release unpins (a point of instances, its prototypes too): each becomes
** the most recently used evictable entry. */
static void cache_release(geometry_cache *c, uint32_t id)
{
    for_point_blobs(c, id, cache_release_blob);
    assert(cache_check(c, NULL) == BRT_OK);
}

/* ##################################################################### */
/* PART II -- SUPPORT, NOT THE PAPER                                     */
/* ##################################################################### */
/*
** What the method needs to run but the paper does not describe: the scene
** file that holds the batching points between build and trace, the
** scheduler's threads and the direct mode.  The mesh readers, ray and hit
** files, statistics, utilities and the pool of threads are below this
** file (mesh.c, base.c).
*/

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
**     16 u64 source stamp  24 u32 batch_tris  28 u32 proxy_res
**     32 u32 batching points  36 u32 triangles  40 u32 top-level nodes
**     44 u32 0  48 u64 geometry bytes (all blobs)
**     56 three sections {u64 offset, u64 size, u64 checksum}:
**        batch table, top-level nodes, DAG pool
**     248 u64 checksum of bytes 0..247
**   blobs: one triangle BVH per batching point (brt_bvh_blob_write), each
**     at a multiple of SCENE_PAGE, so the cache reads whole aligned pages
**   batch table: BATCH_ENTRY_BYTES per batching point: f32 lo[3] hi[3],
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
**     192 u64 batch_instanced (brt_scene_options)
**   batch table entries of BATCH_ENTRY_BYTES_V4: the 80 bytes above, then
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
#define BATCH_ENTRY_BYTES_V4 104
#define PROTO_ENTRY_BYTES 56
#define SECTION_PROTOTYPES 3
#define SCENE_ENDIAN_MARK 0x01020304u
#define SCENE_HEADER_BYTES 256
#define BATCH_ENTRY_BYTES 80
#define SECTION_BATCHES 0
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

static uint64_t round_up_page(uint64_t n)
{
    return (n + SCENE_PAGE - 1) / SCENE_PAGE * SCENE_PAGE;
}

static void batch_entry_pack(const batch_entry *b, unsigned char *p)
{
    int a;
    memset(p, 0, BATCH_ENTRY_BYTES);
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
static void batch_entry_pack_v4(const batch_entry *b, unsigned char *p)
{
    memset(p, 0, BATCH_ENTRY_BYTES_V4);
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

static void batch_entry_unpack(const unsigned char *p, batch_entry *b)
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
static void top_node_pad(top_node *n)
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
    brt_put_le32(p + 24, h->batch_tris);
    brt_put_le32(p + 28, h->proxy_res);
    brt_put_le32(p + 32, h->batch_count);
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
        brt_put_le64(p + 192, h->batch_instanced);
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
    h->batch_tris = brt_get_le32(p + 24);
    h->proxy_res = brt_get_le32(p + 28);
    h->batch_count = brt_get_le32(p + 32);
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
    h->batch_instanced = 0;
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
        h->batch_instanced = brt_get_le64(p + 192);
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
**           splits above into batching points of at most batch_tris
**           triangles; each gets its BVH blob, written at the next page of
**           the scene file, its proxy in the shared DAG, and a table entry.
**           A mesh that fits one bucket is partitioned exactly as a whole
**           in-memory median split would (the same file as before).
**   tables  the top-level BVH, the batch table and the DAG, then the header
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
#define CELL_BITS 7                                 /* per axis */
#define CELL_COUNT (1u << (3 * CELL_BITS))          /* Morton cells of a split */
#define NO_CHILD 0xFFFFFFFFu
#define BUCKET_BYTES ((size_t)64 << 20)             /* records of one bucket */
#define SCATTER_BYTES ((size_t)16 << 20)            /* all write buffers of a split */
#define SPILL_CHUNK 16384u                          /* records per read and buffer */

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

static void scene_options_resolve(const brt_scene_options *opt, uint32_t *batch_tris,
                                  uint32_t *res)
{
    *batch_tris = opt && opt->batch_tris ? opt->batch_tris : 100000;
    *res = opt && opt->proxy_res ? opt->proxy_res : 128;
}

/* Everything written while a scene file is built. */
typedef struct scene_writer {
    const char *path;           /* final name, for messages */
    int fd;
    uint64_t offset;            /* next free, page-aligned */
    uint32_t res;
    brt_svdag *dag;
    batch_entry *batches;       /* the per-point tables, grown as points come */
    float *boxes;               /* 6 floats per batching point */
    uint32_t batch_count;
    size_t batch_cap;
    uint64_t geometry_bytes;
} scene_writer;

struct instance_build;

typedef struct scene_builder {
    scene_writer w;
    int spill_fd;
    uint64_t spill_end;         /* records in the spill file */
    const volatile sig_atomic_t *interrupt;
    uint32_t batch_tris, bucket_tris, chunk;
    uint32_t instance_bucket;   /* instances of one bucket of the instance pass */
    uint64_t batch_instanced;   /* brt_scene_options.batch_instanced */
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

static void bounds_grow(float lo[3], float hi[3], const float p[3])
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
    return read_fully(b->spill_fd, recs, (size_t)n * sizeof *recs, first * sizeof *recs,
                      pread_reader, NULL, NULL, b->w.path, err);
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
    bounds_grow(o->b.lo, o->b.hi, c);
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
static batch_entry *batch_append(scene_writer *w)
{
    if (w->batch_count == w->batch_cap) {
        size_t need = (size_t)w->batch_count + 1, cap = w->batch_cap, box_cap = w->batch_cap;
        batch_entry *batches = brt_grow(w->batches, &cap, need, sizeof *batches);
        float *boxes;
        if (batches) w->batches = batches;
        boxes = batches ? brt_grow(w->boxes, &box_cap, need, 6 * sizeof *boxes) : NULL;
        if (!boxes || need > MAX_COUNT) return NULL;
        w->boxes = boxes;
        w->batch_cap = cap;         /* box_cap too: both grew from batch_cap to need */
    }
    memset(&w->batches[w->batch_count], 0, sizeof *w->batches);
    return &w->batches[w->batch_count++];
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
        bounds_grow(pw->lo, pw->hi, rec->v);
        bounds_grow(pw->lo, pw->hi, rec->v + 3);
        bounds_grow(pw->lo, pw->hi, rec->v + 6);
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
    batch_entry *e;
    brt_result r = poll_interrupt(b, err);
    if (r != BRT_OK) return r;
    if (pw->bvh_result != BRT_OK)
        return brt_fail(err, pw->bvh_result, "%s: building a batching point's BVH: %s",
                        w->path, brt_result_string(pw->bvh_result));
    if (!pw->blob || !(e = batch_append(w))) return brt_fail(err, BRT_ENOMEM, "%s: out of memory", w->path);
    memcpy(e->lo, pw->lo, sizeof e->lo);
    memcpy(e->hi, pw->hi, sizeof e->hi);
    e->triangles = pw->count;
    e->size = pw->size;
    e->checksum = pw->checksum;
    e->offset = w->offset;
    if ((r = write_at(w->fd, pw->blob, pw->size, e->offset, w->path, err)) != BRT_OK) return r;
    w->offset = round_up_page(e->offset + e->size);
    w->geometry_bytes += e->size;
    memcpy(w->boxes + 6 * (size_t)(w->batch_count - 1), e->lo, 3 * sizeof(float));
    memcpy(w->boxes + 6 * (size_t)(w->batch_count - 1) + 3, e->hi, 3 * sizeof(float));
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
    if (partition_split(&b->points, b->centroids, 0, bk->count, b->batch_tris) != BRT_OK ||
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

/* The direct mode's stream helpers (Part II, "the direct mode's world"):
** a triangle stream gathered into a BVH. */
static brt_result stream_bvh(brt_result (*run)(const void *, uint32_t, brt_triangle_fn, void *,
                                               brt_error *),
                             const void *user, uint32_t id, brt_bvh **out, uint32_t *count,
                             float *lo, float *hi, brt_error *err);
static brt_result run_prototype_stream(const void *user, uint32_t id, brt_triangle_fn emit,
                                       void *emit_user, brt_error *err);

/* ---- instance points ---- */
/*
** An instanced scene (brt_scene_build_source) gets, after the batching
** points of its world triangles, the blobs of its prototypes (one BVH
** each, written once) and batching points of instances, cut a bucket at
** a time by partition_by_size (the instance pass, below); each point's
** blob is its instance table:
**   0 "BRTINSTS"  8 u32 instances n  12 u32 tree nodes m  16 u32
**   distinct prototypes k  20 u32 0  24 u64 instanced triangles
**   32 k u32 prototype ids, ascending, then zeros to a multiple of 8
**   n records of INSTANCE_RECORD_BYTES: u32 instance number, u32 prototype,
**     f32 xform[12]
**   m tree nodes of 16 bytes: u32 child[4] (TOP_EMPTY, a node index, or
**     TOP_LEAF | record), the 4-wide tree of top_build over the
**     instances' world boxes
** The tree's boxes are not stored: a load recomputes them from the
** instances and the prototypes' boxes (instance_table_open), so no table,
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
    uint32_t *stamp, stamp_now;     /* range_size's marks, per prototype */
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
    if ((r = instance_admit(in, number, ib->proto_count, &frame, err)) != BRT_OK) return r;
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
        r = read_fully(b->instance_fd, data, sizeof data,
                       (uint64_t)ib->recs[i].prim * INSTANCE_DATA_BYTES, pread_reader, NULL, NULL,
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
        brt_result r = stream_bvh(run_prototype_stream, source, p, &ib->protos[p], &e->triangles,
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
        b->w.offset = round_up_page(e->offset + e->size);
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
    margin_begin(m, lo, hi);
    for (i = 0; i < n; i++) {
        const uint32_t k = slots ? slots[i] : i;
        brt_instance_frame f;
        if (brt_instance_frame_init(&ib->items[k], 0, &f, NULL) == BRT_OK) margin_add(m, &f, ib->radii[k]);
    }
}

/* The proxy of a point of instances: each instance voxelized through its
** prototype's BVH, dilated by INSTANCE_DILATION of a voxel.  The grid
** covers the point's box grown by a sixteenth of a voxel, more than the
** dilation, so that what the dilation marks beyond the box is inside. */
static brt_result instance_point_proxy(const instance_build *ib, const instance_point *ip,
                                       const float lo[3], const float hi[3], uint32_t res,
                                       brt_grid *grid)
{
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
                                  INSTANCE_DILATION * grid->cell);
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
    batch_entry *e = NULL;
    brt_grid grid;
    brt_result r = poll_interrupt(b, err);
    grid.bits = NULL;
    ip.items = ib->items;
    ip.numbers = ib->numbers;
    ip.slots = slots;
    ip.n = n;
    for (i = 0; boxes && i < n; i++) memcpy(boxes + 6 * (size_t)i, ib->boxes + 6 * (size_t)slots[i], 6 * sizeof *boxes);
    if (r == BRT_OK && (!boxes || !(uses = instance_point_uses(ib, &ip)) ||
                        top_build(boxes, n, &nodes, &ip.m) != BRT_OK ||
                        !(blob = malloc(instance_table_bytes(n, ip.m, ip.k))) || !(e = batch_append(w))))
        r = brt_fail(err, BRT_ENOMEM, "%s: out of memory", w->path);
    if (r == BRT_OK) {
        ip.nodes = nodes;
        ip.uses = uses;
        instance_table_pack(&ip, blob);
        bounds_clear(e->lo, e->hi);
        for (i = 0; i < n; i++) {
            bounds_grow(e->lo, e->hi, boxes + 6 * (size_t)i);
            bounds_grow(e->lo, e->hi, boxes + 6 * (size_t)i + 3);
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
        w->offset = round_up_page(e->offset + e->size);
        w->geometry_bytes += e->size;
        memcpy(w->boxes + 6 * (size_t)(w->batch_count - 1), e->lo, 3 * sizeof(float));
        memcpy(w->boxes + 6 * (size_t)(w->batch_count - 1) + 3, e->hi, 3 * sizeof(float));
        r = instance_point_proxy(ib, &ip, e->lo, e->hi, w->res, &grid);
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
** back, partitioned by partition_by_size, each part written as a point. */
static brt_result instance_bucket(scene_builder *b, const bucket *bk, brt_error *err)
{
    instance_build *ib = b->ib;
    partition parts;
    size_limits limits;
    uint32_t i;
    brt_result r = instance_bucket_read(b, ib, bk, err);
    memset(&parts, 0, sizeof parts);
    if (r != BRT_OK) return r;
    limits.batch_tris = b->batch_tris;
    limits.batch_instanced = b->batch_instanced;
    if (!(parts.order = malloc((size_t)ib->count * sizeof *parts.order)))
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", b->w.path);
    for (i = 0; i < ib->count; i++) parts.order[i] = i;
    r = partition_by_size(&parts, ib->centres, 0, ib->count, &limits, instance_range_size, ib);
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
    w->offset = round_up_page(w->offset + size);
    return write_at(w->fd, data, size, s->offset, w->path, err);
}

/* The batch table, the top-level nodes and the DAG pool, (instanced:
** the prototype table,) then the header. */
static brt_result write_tables(scene_writer *w, scene_header *h, const proto_entry *protos,
                               brt_error *err)
{
    const size_t entry_bytes = header_instanced(h) ? BATCH_ENTRY_BYTES_V4 : BATCH_ENTRY_BYTES;
    const size_t proto_bytes = (size_t)h->prototype_count * PROTO_ENTRY_BYTES;
    size_t top_bytes, dag_bytes, table_bytes = (size_t)h->batch_count * entry_bytes;
    top_node *nodes = NULL;
    unsigned char *buf, header[SCENE_HEADER_BYTES];
    uint32_t i;
    brt_result r = top_build(w->boxes, h->batch_count, &nodes, &h->top_node_count);
    if (r != BRT_OK) return brt_fail(err, r, "%s: out of memory", w->path);
    top_bytes = (size_t)h->top_node_count * TOP_NODE_BYTES;
    dag_bytes = brt_svdag_blob_size(w->dag);
    buf = malloc(table_bytes + top_bytes + dag_bytes + proto_bytes + 1);
    if (!buf) {
        free(nodes);
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", w->path);
    }
    for (i = 0; i < h->batch_count; i++) {
        if (header_instanced(h)) batch_entry_pack_v4(&w->batches[i], buf + (size_t)i * entry_bytes);
        else batch_entry_pack(&w->batches[i], buf + (size_t)i * entry_bytes);
    }
    for (i = 0; i < h->prototype_count; i++)
        proto_entry_pack(&protos[i], buf + table_bytes + top_bytes + dag_bytes + (size_t)i * PROTO_ENTRY_BYTES);
    for (i = 0; i < h->top_node_count; i++) top_node_pack(&nodes[i], buf + table_bytes + (size_t)i * TOP_NODE_BYTES);
    brt_svdag_blob_write(w->dag, buf + table_bytes + top_bytes);
    free(nodes);
    r = write_section(w, buf, table_bytes, &h->sections[SECTION_BATCHES], err);
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
    size_t point = most < b->batch_tris ? most : b->batch_tris;
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
    h->batch_count = b->w.batch_count;
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
    for (i = 0; i < w->batch_count; i++) {
        bounds_grow(lo, hi, w->boxes + 6 * (size_t)i);
        bounds_grow(lo, hi, w->boxes + 6 * (size_t)i + 3);
    }
    margin_begin(m, lo, hi);
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
    if (r == BRT_OK && b->w.batch_count == 0)
        r = brt_fail(err, BRT_EARG, "%s: the scene has no triangles", b->w.path);
    if (r == BRT_OK) {
        h->batch_count = b->w.batch_count;
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
    free(b->w.batches);
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
    b->batch_instanced = opt ? opt->batch_instanced : 0;
    brt_pool_init(&b->pool, opt ? opt->threads : 0);
    scene_options_resolve(opt, &b->batch_tris, &b->w.res);
    if (!brt_proxy_res_valid(b->w.res))
        return brt_fail(err, BRT_EARG, "proxy resolution %u is not a power of two in 2..1024", b->w.res);
    /* A bucket of instances holds about four times the bytes of a spill
    ** record per instance, so it holds a quarter as many. */
    b->instance_bucket = cap / 4 > 0 ? cap / 4 : 1;
    b->bucket_tris = cap / b->batch_tris * b->batch_tris;
    if (b->bucket_tris < b->batch_tris) b->bucket_tris = b->batch_tris;
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
    h.batch_tris = b.batch_tris;
    h.proxy_res = b.w.res;
    h.stamp = source_stamp;
    h.batch_instanced = instanced ? b.batch_instanced : 0;
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
static brt_result read_fully(int fd, void *buf, size_t size, uint64_t offset,
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
static long pread_reader(int fd, void *buf, size_t size, uint64_t offset, void *user)
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
    r = read_fully(s->fd, buf, sec->size, sec->offset, pread_reader, NULL, NULL, s->path, err);
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
**   check_batches  the table against the header: triangles and bytes add up
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
    if (h->batch_count == 0)
        return brt_fail(err, BRT_EFORMAT, "%s: header: no batching points", s->path);
    if (h->top_node_count == 0 || h->top_node_count > h->batch_count)
        return brt_fail(err, BRT_EFORMAT, "%s: header: %u top-level nodes for %u batching points",
                        s->path, h->top_node_count, h->batch_count);
    if (h->sections[SECTION_BATCHES].size !=
        (uint64_t)h->batch_count * (header_instanced(h) ? BATCH_ENTRY_BYTES_V4 : BATCH_ENTRY_BYTES))
        return brt_fail(err, BRT_EFORMAT, "%s: header: batch table has the wrong size", s->path);
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
           offset <= s->file_size - round_up_page(size);
}

/* One batch table entry: its box, its blob inside the file (whole pages,
** as the cache reads them), its proxy. */
static brt_result check_batch(const brt_scene *s, uint32_t i, const batch_entry *b, brt_error *err)
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
static brt_result check_batches(const brt_scene *s, brt_error *err)
{
    uint64_t triangles = 0, bytes = 0;
    uint32_t i;
    for (i = 0; i < s->header.batch_count; i++) {
        brt_result r = check_batch(s, i, &s->batches[i], err);
        if (r != BRT_OK) return r;
        if (!s->batches[i].instances) triangles += s->batches[i].triangles;
        bytes += s->batches[i].size;
    }
    for (i = 0; i < s->header.prototype_count; i++) bytes += s->prototypes[i].size;
    if (triangles != s->header.triangle_count)
        return brt_fail(err, BRT_EFORMAT, "%s: batch table: batching points hold %llu triangles, "
                        "header says %u", s->path, (unsigned long long)triangles,
                        s->header.triangle_count);
    if (bytes != s->header.geometry_bytes)
        return brt_fail(err, BRT_EFORMAT, "%s: batch table: blobs hold %llu bytes, header says %llu",
                        s->path, (unsigned long long)bytes,
                        (unsigned long long)s->header.geometry_bytes);
    return BRT_OK;
}

/* The frame of a batching point's inner proxy, as the build made it: the
** grid brt_grid_init fits to its box at inner_res (res 0, which no check
** passes, when the box is not valid: check_batch names that first).
** brt_grid_init allocates the grid's bits too, so it can run out of
** memory: that is reported as such, not as an invalid inner proxy. */
static brt_result inner_frame(batch_entry *b, uint32_t proxy_res)
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

static brt_result load_batches(brt_scene *s, brt_error *err)
{
    unsigned char *table;
    uint32_t i;
    brt_result r = read_section(s, SECTION_BATCHES, "batch table", (void **)&table, err);
    if (r != BRT_OK) return r;
    s->batches = malloc(((size_t)s->header.batch_count + 1) * sizeof *s->batches);
    if (!s->batches) {
        free(table);
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    }
    for (i = 0; i < s->header.batch_count; i++) {
        const size_t bytes = header_instanced(&s->header) ? BATCH_ENTRY_BYTES_V4 : BATCH_ENTRY_BYTES;
        const unsigned char *p = table + (size_t)i * bytes;
        batch_entry_unpack(p, &s->batches[i]);
        if (header_instanced(&s->header)) {
            batch_entry *e = &s->batches[i];
            e->instances = brt_get_le32(p + 80);
            e->instanced = brt_get_le64(p + 88);
            margin_begin(&e->margin, e->lo, e->hi);
            e->margin.condition = get_f32(p + 84);
            e->margin.reach = get_f32(p + 96);
        }
        if (inner_frame(&s->batches[i], s->header.proxy_res) != BRT_OK) {
            free(table);
            return brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
        }
    }
    free(table);
    return check_batches(s, err);
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
        if (c >= s->header.batch_count || seen[c]++)
            return brt_fail(err, BRT_EFORMAT, "%s: top-level node %u: bad leaf", s->path, i);
        if (!lane_holds(n, lane, s->batches[c].lo, s->batches[c].hi))
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
** boxes, before top_node_pad. */
static brt_result check_top(brt_scene *s, brt_error *err)
{
    uint32_t n = s->header.top_node_count, count = s->header.batch_count, i;
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
    for (i = 0; r == BRT_OK && i < s->header.top_node_count; i++) top_node_pad(&s->top[i]);
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
    const uint32_t n = s->header.batch_count + s->header.prototype_count;
    blob_place *sorted = malloc((size_t)n * sizeof *sorted);
    uint64_t free_from = SCENE_PAGE;
    uint32_t i;
    if (!sorted) return brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    memcpy(sorted, s->blobs, (size_t)n * sizeof *sorted);
    qsort(sorted, n, sizeof *sorted, blob_offset_order);
    for (i = 0; i < n && sorted[i].offset >= free_from; i++)
        free_from = sorted[i].offset + round_up_page(sorted[i].size);   /* blob_inside: no wrap */
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
    const uint32_t b = s->header.batch_count;
    uint32_t i;
    s->blobs = malloc(((size_t)b + s->header.prototype_count) * sizeof *s->blobs);
    if (!s->blobs) return brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    for (i = 0; i < b; i++) {
        s->blobs[i].offset = s->batches[i].offset;
        s->blobs[i].size = s->batches[i].size;
        s->blobs[i].checksum = s->batches[i].checksum;
    }
    for (i = 0; i < s->header.prototype_count; i++) {
        s->blobs[b + i].offset = s->prototypes[i].offset;
        s->blobs[b + i].size = s->prototypes[i].size;
        s->blobs[b + i].checksum = s->prototypes[i].checksum;
    }
    return check_blobs_apart(s, err);
}

static brt_result load_dag(brt_scene *s, brt_error *err)
{
    brt_error why;
    brt_result r = read_section(s, SECTION_DAG, "proxy pool", &s->dag_blob, err);
    if (r != BRT_OK) return r;
    r = brt_svdag_blob_open(s->dag_blob, s->header.sections[SECTION_DAG].size, &s->dag, &why);
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
        r = read_fully(s->fd, header, sizeof header, 0, pread_reader, NULL, NULL, scene_path, err);
    if (r == BRT_OK) r = header_unpack(scene_path, header, &s->header, err);
    if (r == BRT_OK) r = check_header(s, err);
    if (r == BRT_OK) r = load_dag(s, err);
    if (r == BRT_OK) r = load_prototypes(s, err);
    if (r == BRT_OK) r = load_batches(s, err);
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
    free(s->dag_blob);
    free(s->batches);
    free(s->prototypes);
    free(s->blobs);
    free(s->top);
    free(s->path);
    free(s);
}

int brt_scene_matches(const brt_scene *s, uint64_t stamp, const brt_scene_options *opt)
{
    uint32_t batch_tris, res;
    scene_options_resolve(opt, &batch_tris, &res);
    return s->header.stamp == stamp && s->header.batch_tris == batch_tris &&
           s->header.proxy_res == res &&
           s->header.batch_instanced == (opt && s->header.prototype_count ? opt->batch_instanced : 0);
}

uint32_t brt_scene_batch_count(const brt_scene *s) { return s->header.batch_count; }
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
    for (i = 0; i < s->header.batch_count; i++)
        for (a = 0; a < 3; a++) {
            if (s->batches[i].lo[a] < bmin[a]) bmin[a] = s->batches[i].lo[a];
            if (s->batches[i].hi[a] > bmax[a]) bmax[a] = s->batches[i].hi[a];
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
        margin_add(&set->margin, &set->frames[i], radius);
    }
    /* The entry's margin gated the proxy before this load: it must cover
    ** the instances (a smaller one would have let rays through that the
    ** proxy's dilation does not cover). */
    if (set->margin.condition > s->batches[id].margin.condition ||
        set->margin.reach > s->batches[id].margin.reach)
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
            top_lane_clear(n, lane);
            n->child[lane] = c;
            if (c & TOP_LEAF) {
                top_lane_grow(n, lane, boxes + 6 * (size_t)(c & ~TOP_LEAF));
                continue;
            }
            for (k = 0; k < 4; k++) {
                float box[6];
                if (set->nodes[c].child[k] == TOP_EMPTY) continue;
                for (a = 0; a < 6; a++) box[a] = set->nodes[c].box[a][k];
                top_lane_grow(n, lane, box);
            }
        }
    }
    for (i = 0; i < set->node_count; i++) top_node_pad(&set->nodes[i]);
}

static brt_result table_alloc(instance_set *set, uint32_t n, uint32_t m, uint32_t k)
{
    set->count = n;
    set->node_count = m;
    set->use_count = k;
    set->ids = malloc((size_t)n * sizeof *set->ids);
    set->prototypes = malloc((size_t)n * sizeof *set->prototypes);
    set->frames = malloc((size_t)n * sizeof *set->frames);
    set->nodes = malloc((size_t)m * sizeof *set->nodes);
    set->uses = malloc((size_t)k * sizeof *set->uses);
    return set->ids && set->prototypes && set->frames && set->nodes && set->uses ? BRT_OK : BRT_ENOMEM;
}

/* Opens point id's instance table (size bytes at data, checksum already
** checked): every field validated, the boxes recomputed. */
static brt_result instance_table_open(const brt_scene *s, uint32_t id, const unsigned char *data,
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
    if (n == 0 || m == 0 || m > n || k == 0 || k > n || n != s->batches[id].instances ||
        size != instance_table_bytes(n, m, k))
        r = table_fail(s, id, err, "counts disagree with its size or its table entry");
    else if (table_alloc(set, n, m, k) != BRT_OK || !(marks = calloc((size_t)n + m, 1)) ||
             !(boxes = malloc(6 * (size_t)n * sizeof *boxes)))
        r = brt_fail(err, BRT_ENOMEM, "%s: out of memory", s->path);
    margin_begin(&set->margin, s->batches[id].lo, s->batches[id].hi);
    if (r == BRT_OK) r = table_uses(s, id, data + INSTANCE_TABLE_HEADER, set, err);
    data += INSTANCE_TABLE_HEADER + ((size_t)k * 4 + 7) / 8 * 8;
    if (r == BRT_OK) r = table_records(s, id, data, set, boxes, err);
    if (r == BRT_OK)
        r = table_tree(s, id, data + (size_t)n * INSTANCE_RECORD_BYTES, set, marks, marks + n, err);
    if (r == BRT_OK) table_boxes(set, boxes);
    free(marks);
    free(boxes);
    if (r != BRT_OK) {
        set_free(set);
        free(set);
        return r;
    }
    *out = set;
    return BRT_OK;
}

/* ---- the partition checker ------------------------------------------ */

/* Marks number k in a bitmap: 0 when it was marked already. */
static int mark_once(unsigned char *seen, uint32_t k)
{
    if (seen[k >> 3] & (1u << (k & 7))) return 0;
    seen[k >> 3] |= (unsigned char)(1u << (k & 7));
    return 1;
}

/* Marks the triangles of a point of world triangles in seen[]. */
static brt_result check_triangles(const brt_scene *s, uint32_t id, const brt_bvh *bvh,
                                  unsigned char *seen, brt_error *err)
{
    const uint32_t *prims = brt_bvh_prim_ids(bvh);
    uint32_t k, n = brt_bvh_triangle_count(bvh);
    if (n != s->batches[id].triangles)
        return brt_fail(err, BRT_ECHECK, "%s: batching point %u: its BVH holds %u triangles, "
                        "its table entry %u", s->path, id, n, s->batches[id].triangles);
    for (k = 0; k < n; k++) {
        if (prims[k] >= s->header.triangle_count)
            return brt_fail(err, BRT_ECHECK, "%s: batching point %u: triangle %u out of range "
                            "(%u triangles)", s->path, id, prims[k], s->header.triangle_count);
        if (!mark_once(seen, prims[k]))
            return brt_fail(err, BRT_ECHECK, "%s: triangle %u is in two batching points "
                            "(again in %u)", s->path, prims[k], id);
    }
    return BRT_OK;
}

/* Marks the instances of a point of instances in seen_inst[]; its size,
** the triangles of its distinct prototypes, may exceed batch_tris only
** when it uses one prototype. */
static brt_result check_instances(const brt_scene *s, uint32_t id, const instance_set *set,
                                  uint32_t batch_tris, unsigned char *seen_inst, brt_error *err)
{
    uint64_t size = 0;
    uint32_t k;
    for (k = 0; k < set->use_count; k++) size += s->prototypes[set->uses[k]].triangles;
    if (size > batch_tris && set->use_count > 1)
        return brt_fail(err, BRT_ECHECK, "%s: batching point %u: %llu triangles of %u prototypes, "
                        "more than %u", s->path, id, (unsigned long long)size, set->use_count, batch_tris);
    for (k = 0; k < set->count; k++)
        if (!mark_once(seen_inst, set->ids[k]))
            return brt_fail(err, BRT_ECHECK, "%s: instance %u is in two batching points (again in %u)",
                            s->path, set->ids[k], id);
    return BRT_OK;
}

/* Reads point id and marks what it holds. */
static brt_result check_point(const geometry_cache *c, uint32_t id, uint32_t batch_tris,
                              unsigned char *seen, unsigned char *seen_inst, brt_error *err)
{
    const brt_scene *s = c->scene;
    uint64_t bytes = 0;
    void *data = NULL;
    blob_view view;
    brt_result r;
    if (!s->batches[id].instances && s->batches[id].triangles > batch_tris)
        return brt_fail(err, BRT_ECHECK, "%s: batching point %u holds %u triangles, more than %u",
                        s->path, id, s->batches[id].triangles, batch_tris);
    if ((r = blob_read(c, id, &bytes, &data, &view, err)) != BRT_OK) return r;
    r = view.set ? check_instances(s, id, view.set, batch_tris, seen_inst, err)
                 : check_triangles(s, id, view.bvh, seen, err);
    view_free(&view);
    blob_free(s, id, data);
    return r;
}

/* Every instance is in one point, except those of empty prototypes. */
static int instance_may_be_absent(const brt_scene *s)
{
    uint32_t p;
    for (p = 0; p < s->header.prototype_count; p++)
        if (s->prototypes[p].triangles == 0) return 1;
    return 0;
}

brt_result brt_scene_check_partition(const brt_scene *scene, uint32_t batch_tris,
                                     brt_error *err)
{
    uint32_t n = scene->header.triangle_count, m = scene->header.instance_count, id, t;
    unsigned char *seen = calloc((size_t)n / 8 + 1, 1), *seen_inst = calloc((size_t)m / 8 + 1, 1);
    geometry_cache c;
    brt_result r = BRT_OK;
    if (!seen || !seen_inst) r = brt_fail(err, BRT_ENOMEM, "%s: out of memory", scene->path);
    memset(&c, 0, sizeof c);
    c.scene = (brt_scene *)scene;   /* blob_read only reads through it */
    c.read_fn = pread_reader;
    for (id = 0; id < scene->header.batch_count && r == BRT_OK; id++)
        r = check_point(&c, id, batch_tris, seen, seen_inst, err);
    for (t = 0; t < n && r == BRT_OK; t++)
        if (!(seen[t >> 3] & (1u << (t & 7))))
            r = brt_fail(err, BRT_ECHECK, "%s: triangle %u is in no batching point", scene->path, t);
    for (t = 0; t < m && r == BRT_OK && !instance_may_be_absent(scene); t++)
        if (!(seen_inst[t >> 3] & (1u << (t & 7))))
            r = brt_fail(err, BRT_ECHECK, "%s: instance %u is in no batching point", scene->path, t);
    free(seen);
    free(seen_inst);
    return r;
}

/* ---- the scheduler's loop on threads: layers 4 and 5 ---------------- */
/*
** The plain loop of Part I (run_rays) intersects a batch's rays, releases
** the batching point and walks each ray on and settles it, one after
** another.  With more than one thread the same work runs in PHASES: a
** phase is the list of rays that run_rays would loop over.  The rays are
** split across the pool's threads; walk_on reads the shared state (top-
** level BVH, proxies, resident BVHs) and writes only its ray's slot, its
** outcome and its thread's walker.  The calling thread settles the rays
** in list order as their chunks finish (phase_settle), and after the
** phase the LRU order is updated from a log of the walks' uses of
** resident batching points (use_log), as if the rays had walked one after
** another.  So every decision -- which queue is fullest, what is evicted,
** the order of finished calls -- is the plain loop's; the threads: tests
** hold the two byte-equal, and make bench-threads prints the wall
** seconds at 1 and 2 threads.
**
** Layer 4, read-ahead: while a phase runs, the cache's own thread reads
** the blob of the fullest queue left, the likely next load
** (cache_read_ahead).  It changes no count and no decision, only the wall
** time: make bench-threads's row "render 25%, --disk-speed 100M" (one
** thread reads nothing ahead).
*/
struct use_log {
    uint64_t stamp;             /* the current ray's place in its phase (high
                                ** word) and its uses so far (low word) */
    uint64_t *used_at;          /* per batching point: stamp of its last use; 0: none */
    uint32_t *used, used_count; /* the points used, in first-use order */
};

/* A batching point used by a phase and the stamp of its last use. */
typedef struct point_use {
    uint64_t stamp;
    uint32_t id;
} point_use;

struct phase_threads {
    brt_pool pool;
    walker *walkers;            /* one per thread of the pool */
    use_log *logs;              /* one per walker */
    uint32_t *outcome;          /* per ray of a phase: where its walk stopped */
    point_use *uses;            /* a phase's uses, merged */
};

/* The walker of a thread records a use, stamped in walk order. */
static void use_log_record(use_log *log, uint32_t id)
{
    if (log->used_at[id] == 0) log->used[log->used_count++] = id;
    log->used_at[id] = log->stamp++;
}

static void use_log_free(use_log *log)
{
    free(log->used_at);
    free(log->used);
}

/* A phase: the rays in slots[0..count), first intersected with bvh when
** it is not NULL (the batching point whose queue they are). */
typedef struct phase_job {
    scheduler *s;
    const uint32_t *slots;
    const geometry *g;
    brt_result result;          /* of the settling: BRT_ENOMEM from a queue */
} phase_job;

static void phase_chunk(void *ctx, unsigned thread, size_t first, size_t end)
{
    const phase_job *j = ctx;
    scheduler *s = j->s;
    walker *w = &s->threads->walkers[thread];
    size_t i;
    for (i = first; i < end; i++) {
        ray_slot *r = &s->slots[j->slots[i]];
        w->uses->stamp = (uint64_t)(i + 1) << 32;   /* ray i's uses come after ray i-1's */
        if (j->g) intersect_slot(s, j->g, r, NULL);
        s->threads->outcome[i] = walk_on(s, w, r);
    }
}

/* Settles rays [first, end) of a phase, in order. */
static void phase_settle(void *ctx, size_t first, size_t end)
{
    phase_job *j = ctx;
    size_t i;
    for (i = first; i < end && j->result == BRT_OK; i++)
        j->result = settle(j->s, j->slots[i], j->s->threads->outcome[i]);
}

static int use_before(const void *a, const void *b)
{
    uint64_t x = ((const point_use *)a)->stamp, y = ((const point_use *)b)->stamp;
    return (x > y) - (x < y);
}

/* The LRU order after a phase: each resident batching point it used moves
** to the back in the order of its last use over all threads -- the order
** the plain loop's touches leave. */
static void uses_replay(scheduler *s)
{
    phase_threads *t = s->threads;
    use_log *all = &t->logs[0];   /* thread 0's log gathers the others' */
    uint32_t i, k, n;
    for (i = 1; i < t->pool.count; i++) {
        use_log *log = &t->logs[i];
        for (k = 0; k < log->used_count; k++) {
            uint32_t id = log->used[k];
            if (all->used_at[id] == 0) all->used[all->used_count++] = id;
            if (log->used_at[id] > all->used_at[id]) all->used_at[id] = log->used_at[id];
            log->used_at[id] = 0;
        }
        log->used_count = 0;
    }
    for (n = 0; n < all->used_count; n++) {
        t->uses[n].id = all->used[n];
        t->uses[n].stamp = all->used_at[all->used[n]];
        all->used_at[all->used[n]] = 0;
    }
    all->used_count = 0;
    qsort(t->uses, n, sizeof *t->uses, use_before);
    for (k = 0; k < n; k++) cache_touch(&s->cache, t->uses[k].id);
}

#define AHEAD_LOOK 15   /* heap slots searched for the next load: the top
                         ** four levels hold the fullest queues (a guess
                         ** costs no decision, so the search stays short) */

/* Layer 4's guess of the next load: the fullest queue whose batching
** point is not in memory, among the heap's first AHEAD_LOOK slots (a
** resident point is served without a load, so the fullest queue alone
** is often no load at all); NO_ENTRY when there is none. */
static uint32_t next_load_guess(const scheduler *s)
{
    uint64_t best = UINT64_MAX;
    uint32_t i;
    for (i = 0; i < s->fullest.size && i < AHEAD_LOOK; i++)
        if (s->fullest.keys[i] < best && !s->cache.entries[(uint32_t)s->fullest.keys[i]].data)
            best = s->fullest.keys[i];
    return best == UINT64_MAX ? NO_ENTRY : (uint32_t)best;
}

#define PHASE_CHUNK 64   /* rays per chunk: many chunks per phase, each far
                         ** longer than a take from the shared counter
                         ** (make bench-threads times the phases) */

/* Layer 5: run_rays in a phase (id: the batching point whose queue it is,
** pinned, or NO_ENTRY for new rays).  Released before the uses are
** replayed, as the plain loop releases it before the walks. */
static brt_result phases_run(scheduler *s, const uint32_t *slots, uint32_t count, uint32_t id,
                             const geometry *g)
{
    phase_job j;
    unsigned i;
    cache_read_ahead(&s->cache, next_load_guess(s));                    /* layer 4 */
    j.s = s;
    j.slots = slots;
    j.g = g;
    j.result = BRT_OK;
    brt_pool_run(&s->threads->pool, phase_chunk, phase_settle, &j, count, PHASE_CHUNK);
    if (id != NO_ENTRY) cache_release(&s->cache, id);
    for (i = 0; i < s->threads->pool.count; i++) walker_count(s, &s->threads->walkers[i]);
    uses_replay(s);
    return j.result;
}

/* The pool and one walker and use log per thread, when there is more
** than one thread (threads: 0 means all cores); else s->threads stays
** NULL and the plain loop runs. */
static brt_result threads_init(scheduler *s, unsigned threads)
{
    uint32_t n = s->scene->header.batch_count, i;
    phase_threads *t;
    if (brt_threads_resolve(threads) < 2) return BRT_OK;
    t = s->threads = calloc(1, sizeof *t);
    if (!t) return BRT_ENOMEM;
    brt_pool_init(&t->pool, threads);
    t->walkers = calloc(t->pool.count, sizeof *t->walkers);
    t->logs = calloc(t->pool.count, sizeof *t->logs);
    t->outcome = malloc((size_t)s->capacity * sizeof *t->outcome);
    t->uses = malloc((size_t)n * sizeof *t->uses);
    if (!t->walkers || !t->logs || !t->outcome || !t->uses) return BRT_ENOMEM;
    for (i = 0; i < t->pool.count; i++) {
        walker *w = &t->walkers[i];
        w->walk.keys = malloc(((size_t)n + s->scene->header.top_node_count) * sizeof *w->walk.keys);
        w->uses = &t->logs[i];
        w->uses->used_at = calloc(n, sizeof *w->uses->used_at);
        w->uses->used = malloc((size_t)n * sizeof *w->uses->used);
        if (!w->walk.keys || !w->uses->used_at || !w->uses->used) return BRT_ENOMEM;
    }
    s->cache.read_ahead = t->pool.count > 1;
    return BRT_OK;
}

static void threads_free(scheduler *s)
{
    phase_threads *t = s->threads;
    uint32_t i;
    if (!t) return;
    for (i = 0; t->walkers && i < t->pool.count; i++) {
        free(t->walkers[i].walk.keys);
        if (t->logs) use_log_free(&t->logs[i]);
    }
    free(t->walkers);
    free(t->logs);
    free(t->outcome);
    free(t->uses);
    brt_pool_free(&t->pool);
    free(t);
    s->threads = NULL;
}

/* ---- direct tracing: chunks of rays through geometry in memory ------ */

typedef struct trace_job {
    geometry geometry;
    const brt_ray *rays;
    const uint64_t *tags;
    brt_hit *hits;
    float *normals;
} trace_job;

static void trace_chunk(void *ctx, unsigned thread, size_t first, size_t end)
{
    const trace_job *j = ctx;
    size_t i;
    (void)thread;
    for (i = first; i < end; i++) {
        float *normal = j->normals ? j->normals + 3 * i : NULL;
        if (normal) normal[0] = normal[1] = normal[2] = 0.0f;
        brt_hit_clear(&j->hits[i]);
        intersect_ray(&j->geometry, &j->rays[i], j->tags ? j->tags[i] : 0, &j->hits[i], normal, NULL);
    }
}

#define TRACE_CHUNK 1024   /* rays per chunk: far longer than a take of the lock */

static void trace_geometry(const geometry *g, const brt_ray *rays, const uint64_t *tags,
                           size_t count, brt_hit *hits, float *normals, unsigned threads)
{
    trace_job j;
    brt_pool p;
    j.geometry = *g;
    j.rays = rays;
    j.tags = tags;
    j.hits = hits;
    j.normals = normals;
    brt_pool_init(&p, count > TRACE_CHUNK ? threads : 1);
    brt_pool_run(&p, trace_chunk, NULL, &j, count, TRACE_CHUNK);
    brt_pool_free(&p);
}

void brt_bvh_trace(const brt_bvh *bvh, const brt_ray *rays, const uint64_t *tags,
                   size_t count, brt_hit *hits, float *normals, unsigned threads)
{
    geometry g;
    g.triangles = bvh;
    g.instances = NULL;
    g.prototypes = NULL;
    trace_geometry(&g, rays, tags, count, hits, normals, threads);
}

/* ---- the direct mode's world: an instanced scene in memory ------------ */

struct brt_world {
    brt_bvh *triangles;             /* the world triangles' BVH (prim: file order) */
    brt_bvh **prototypes;
    uint32_t prototype_count;
    instance_set set;               /* instances of non-empty prototypes */
    uint32_t instance_count;        /* every instance streamed */
    uint64_t unique, instanced;
    float lo[3], hi[3];
};

/* Triangles of a stream gathered as corners (9 floats each), checked to
** arrive numbered in order. */
typedef struct corner_list {
    float *corners;
    size_t capacity;
    uint32_t count;
} corner_list;

static brt_result gather_corners(void *user, const float *corners, uint32_t count,
                                 uint32_t first, brt_error *err)
{
    corner_list *l = user;
    float *grown;
    if (first != l->count || count > UINT32_MAX - l->count)
        return brt_fail(err, BRT_EARG, "triangle stream: chunk numbered %u after %u triangles",
                        (unsigned)first, (unsigned)l->count);
    grown = brt_grow(l->corners, &l->capacity, 9 * ((size_t)l->count + count), sizeof *grown);
    if (!grown) return brt_fail(err, BRT_ENOMEM, "out of memory for %u triangles",
                                (unsigned)(l->count + count));
    l->corners = grown;
    memcpy(l->corners + 9 * (size_t)l->count, corners, 9 * (size_t)count * sizeof *corners);
    l->count += count;
    return BRT_OK;
}

/* The BVH of gathered corners (triangle i numbered i). */
static brt_result corners_bvh(const corner_list *l, brt_bvh **out, brt_error *err)
{
    uint32_t *indices = malloc(3 * (size_t)l->count * sizeof *indices + 1), i;
    brt_result rc;
    if (!indices) return brt_fail(err, BRT_ENOMEM, "out of memory for a BVH");
    for (i = 0; i < 3 * l->count; i++) indices[i] = i;
    rc = brt_bvh_build(l->corners, indices, l->count, NULL, out);
    free(indices);
    return rc == BRT_OK ? BRT_OK
                        : brt_fail(err, rc, "cannot build a BVH of %u triangles: %s",
                                   (unsigned)l->count, brt_result_string(rc));
}

/* Runs a triangle stream into a BVH; *count gets its triangles, and lo,
** hi (when not NULL) grow by their exact bounds. */
static brt_result stream_bvh(brt_result (*run)(const void *, uint32_t, brt_triangle_fn, void *,
                                               brt_error *),
                             const void *user, uint32_t id, brt_bvh **out, uint32_t *count,
                             float *lo, float *hi, brt_error *err)
{
    corner_list l = {NULL, 0, 0};
    brt_result rc = run(user, id, gather_corners, &l, err);
    size_t i;
    if (rc == BRT_OK) rc = corners_bvh(&l, out, err);
    for (i = 0; lo && i < 3 * (size_t)l.count; i++) bounds_grow(lo, hi, l.corners + 3 * i);
    *count = l.count;
    free(l.corners);
    return rc;
}

static brt_result run_world_stream(const void *user, uint32_t id, brt_triangle_fn emit,
                                   void *emit_user, brt_error *err)
{
    const brt_triangle_source *world = user;
    (void)id;
    return world->run(world->user, emit, emit_user, err);
}

static brt_result run_prototype_stream(const void *user, uint32_t id, brt_triangle_fn emit,
                                       void *emit_user, brt_error *err)
{
    const brt_scene_source *source = user;
    return source->prototype(source->user, id, emit, emit_user, err);
}

/* Instances gathered into a world: checked, framed and boxed. */
typedef struct instance_gather {
    brt_world *world;
    const uint32_t *proto_tris;     /* triangles per prototype */
    float *boxes;                   /* 6 per instance of the set */
    float *radii;                   /* 1 per instance of the set */
    size_t id_cap, proto_cap, frame_cap, box_cap, radius_cap;
} instance_gather;

static brt_result gather_instance(instance_gather *g, const brt_instance *in, uint32_t inst,
                                  brt_error *err)
{
    brt_world *w = g->world;
    instance_set *set = &w->set;
    brt_instance_frame frame;
    float olo[3], ohi[3];
    brt_result rc;
    int a;
    if ((rc = instance_admit(in, inst, w->prototype_count, &frame, err)) != BRT_OK) return rc;
    w->instanced += g->proto_tris[in->prototype];
    if (g->proto_tris[in->prototype] == 0) return BRT_OK;   /* never hit */
    if (!(set->ids = brt_grow(set->ids, &g->id_cap, (size_t)set->count + 1, sizeof *set->ids))
        || !(set->prototypes = brt_grow(set->prototypes, &g->proto_cap, (size_t)set->count + 1,
                                        sizeof *set->prototypes))
        || !(set->frames = brt_grow(set->frames, &g->frame_cap, (size_t)set->count + 1,
                                    sizeof *set->frames))
        || !(g->boxes = brt_grow(g->boxes, &g->box_cap, 6 * ((size_t)set->count + 1),
                                 sizeof *g->boxes))
        || !(g->radii = brt_grow(g->radii, &g->radius_cap, (size_t)set->count + 1, sizeof *g->radii)))
        return brt_fail(err, BRT_ENOMEM, "out of memory for %u instances", (unsigned)inst + 1);
    brt_bvh_bounds(w->prototypes[in->prototype], olo, ohi);
    brt_instance_bounds(in, &frame, olo, ohi, g->boxes + 6 * (size_t)set->count,
                        g->boxes + 6 * (size_t)set->count + 3, &g->radii[set->count]);
    for (a = 0; a < 3; a++) {
        if (g->boxes[6 * (size_t)set->count + a] < w->lo[a]) w->lo[a] = g->boxes[6 * (size_t)set->count + a];
        if (g->boxes[6 * (size_t)set->count + 3 + a] > w->hi[a]) w->hi[a] = g->boxes[6 * (size_t)set->count + 3 + a];
    }
    set->ids[set->count] = inst;
    set->prototypes[set->count] = in->prototype;
    set->frames[set->count++] = frame;
    return BRT_OK;
}

static brt_result gather_instances(void *user, const brt_instance *instances, uint32_t count,
                                   uint32_t first, brt_error *err)
{
    instance_gather *g = user;
    uint32_t i;
    if (first != g->world->instance_count || count > UINT32_MAX - first)
        return brt_fail(err, BRT_EARG, "instance stream: chunk numbered %u after %u instances",
                        (unsigned)first, (unsigned)g->world->instance_count);
    for (i = 0; i < count; i++) {
        brt_result rc = gather_instance(g, &instances[i], first + i, err);
        if (rc != BRT_OK) return rc;
        g->world->instance_count++;
    }
    return BRT_OK;
}

static brt_result world_prototypes(brt_world *w, const brt_scene_source *source,
                                   uint32_t *proto_tris, brt_error *err)
{
    uint32_t p;
    for (p = 0; p < w->prototype_count; p++) {
        brt_result rc = stream_bvh(run_prototype_stream, source, p, &w->prototypes[p],
                                   &proto_tris[p], NULL, NULL, err);
        if (rc != BRT_OK) return rc;
        w->unique += proto_tris[p];
    }
    return BRT_OK;
}

static brt_result world_fill(brt_world *w, const brt_scene_source *source, brt_error *err)
{
    instance_gather g;
    uint32_t *proto_tris = calloc((size_t)w->prototype_count + 1, sizeof *proto_tris), n = 0;
    brt_result rc = BRT_OK;
    memset(&g, 0, sizeof g);
    if (!proto_tris) return brt_fail(err, BRT_ENOMEM, "out of memory for the prototypes");
    if (source->world.run)
        rc = stream_bvh(run_world_stream, &source->world, 0, &w->triangles, &n, w->lo, w->hi, err);
    w->unique = w->instanced = n;
    if (rc == BRT_OK) rc = world_prototypes(w, source, proto_tris, err);
    g.world = w;
    g.proto_tris = proto_tris;
    if (rc == BRT_OK && source->instances) rc = source->instances(source->user, gather_instances, &g, err);
    if (rc == BRT_OK && set_build_tree(&w->set, g.boxes) != BRT_OK)
        rc = brt_fail(err, BRT_ENOMEM, "out of memory for the instances' tree");
    if (rc == BRT_OK) set_fit_margin(&w->set, g.boxes, g.radii);
    free(g.boxes);
    free(g.radii);
    free(proto_tris);
    return rc;
}

brt_result brt_world_build(const brt_scene_source *source, brt_world **out, brt_error *err)
{
    brt_world *w = calloc(1, sizeof *w);
    brt_result rc;
    int a;
    *out = NULL;
    if (!w) return brt_fail(err, BRT_ENOMEM, "out of memory for a world");
    for (a = 0; a < 3; a++) { w->lo[a] = INFINITY; w->hi[a] = -INFINITY; }
    w->prototype_count = source->prototype_count;
    w->prototypes = calloc((size_t)w->prototype_count + 1, sizeof *w->prototypes);
    rc = w->prototypes ? world_fill(w, source, err)
                       : brt_fail(err, BRT_ENOMEM, "out of memory for %u prototypes",
                                  (unsigned)w->prototype_count);
    if (rc != BRT_OK) {
        brt_world_free(w);
        return rc;
    }
    *out = w;
    return BRT_OK;
}

void brt_world_free(brt_world *w)
{
    uint32_t p;
    if (!w) return;
    brt_bvh_free(w->triangles);
    for (p = 0; w->prototypes && p < w->prototype_count; p++) brt_bvh_free(w->prototypes[p]);
    free(w->prototypes);
    set_free(&w->set);
    free(w);
}

static geometry world_geometry(const brt_world *w)
{
    geometry g;
    g.triangles = w->triangles;
    g.instances = &w->set;
    g.prototypes = (const brt_bvh *const *)w->prototypes;
    return g;
}

void brt_world_intersect(const brt_world *w, const brt_ray *ray, brt_hit *hit, float normal[3])
{
    const geometry g = world_geometry(w);
    intersect_ray(&g, ray, 0, hit, normal, NULL);
}

int brt_world_occluded(const brt_world *w, const brt_ray *ray)
{
    const geometry g = world_geometry(w);
    brt_hit hit;
    brt_hit_clear(&hit);
    intersect_ray(&g, ray, BRT_TAG_OCCLUSION, &hit, NULL, NULL);
    return hit.t == 0.0f;
}

void brt_world_trace(const brt_world *w, const brt_ray *rays, const uint64_t *tags,
                     size_t count, brt_hit *hits, float *normals, unsigned threads)
{
    const geometry g = world_geometry(w);
    trace_geometry(&g, rays, tags, count, hits, normals, threads);
}

uint32_t brt_world_instance_count(const brt_world *w) { return w->instance_count; }
uint32_t brt_world_prototype_count(const brt_world *w) { return w->prototype_count; }
uint64_t brt_world_unique_triangles(const brt_world *w) { return w->unique; }
uint64_t brt_world_instanced_triangles(const brt_world *w) { return w->instanced; }

void brt_world_bounds(const brt_world *w, float bmin[3], float bmax[3])
{
    memcpy(bmin, w->lo, sizeof w->lo);
    memcpy(bmax, w->hi, sizeof w->hi);
}
