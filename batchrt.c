/*
** batchrt.c -- the out-of-core batched traversal of Pharr et al. 1997 with
** the conservative proxies of Molenaar and Eisemann 2020: everything a ray
** meets from the root of the top-level BVH to its hit, and nothing that is
** a file format, a BVH (bvh.c) or a voxel proxy (svdag.c).
**
** The file reads in three parts.  Part I is the method, in the order a ray
** meets it; Part II is batchrt's layers on the method's loop, one section
** each; Part III is what the method needs to run but the paper does not
** describe.  Each section opens with a comment on its design.
**
** PART I -- THE METHOD
**   the partition into batching points    median splits of triangle centres
**   the top-level BVH over batching points and its restartable walk
**                                          (one binary heap, shared with
**                                          the scheduler)
**   instances                              the level below a batching
**                                          point: instance sets, one
**                                          brt_intersect_ray for every mode
**   the scene in memory                    the types the scheduler works on
**   ray queues and the scheduler           the paper's loop (schedule,
**                                          process_batch, walk_on,
**                                          proxy_test, settle), and the
**                                          layers' hooks in it, declared
**                                          in layer order
**   the paper's loop, plain                the same loop in one function,
**                                          without layers
**                                          (schedule_reference)
**   the geometry cache                     pread, LRU (SQLite's pcache
**                                          shape)
** PART II -- BATCHRT'S LAYERS, in the order of the data flow
**   layer 1 proxies_pay, 2 rays_in_flight (the set-up); 3 inner_stops,
**   4 intersect_resident, 5 exact_proxy_hit (a ray's walk); 6 forward and
**   take_rays, with the owners of batching points (other processes);
**   7 fetch_for (the queue's load); 8 cache_decode (the cache's load);
**   9 cache_read_ahead (the cache's load); 10 clip_to_entry, 11
**   order_batch (a batch's intersections); 12 phases_run (threads)
** PART III -- SUPPORT, NOT THE PAPER
**   the partition checker                  every triangle and instance in
**                                          exactly one batching point
**   direct tracing                         the direct mode's chunks of rays
** Beside and below this file (internal.h draws the layers): scene.c, the
** scene file (format, out-of-core build, open, validation); world.c, the
** direct mode's world; mesh.c, OBJ and PLY input; bvh.c; svdag.c; and
** base.c (rays and hits, statistics, errors, utilities, the pool).  The
** data flow is drawn once, in README.md ("The data flow").
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

/* TUNABLES: one line each on why; no answer depends on them, only time
** and memory (the sections named say more, and which command measures). */
#define OUT_OF_CORE_RAYS (1u << 20)  /* rays in flight out of core: many rays
                                     ** gather at a point before its load */
#define IN_CORE_RAYS 4096u           /* rays in flight in core (layer 2): no load
                                     ** repeats, and few rays keep the caches */
#define ARRIVALS_PER_TAKE 1024u      /* rays taken from the exchange per call
                                     ** (layer 6): one buffer, bounded */
#define CACHE_READ_CHUNK ((size_t)8 << 20)   /* bytes per pread of a blob: a
                                     ** bounded request, large enough to stream */
#define AHEAD_LOOK 15                /* heap slots searched for the next load
                                     ** (layer 9): the top four levels hold the
                                     ** fullest queues; a guess decides nothing */
#define PHASE_CHUNK 64               /* rays per chunk of a phase (layer 12):
                                     ** far longer than a take from the shared
                                     ** counter (make bench-threads) */
#define TRACE_CHUNK 1024             /* rays per chunk of the direct mode's
                                     ** threads: far longer than a take of the lock */

/* ##################################################################### */
/* PART I -- THE METHOD: out-of-core batched traversal                   */
/* ##################################################################### */
/*
** Pharr et al. 1997 with the proxies of Molenaar and Eisemann 2020, in the
** order of the data flow (drawn in README.md): the partition into batching
** points, the top-level BVH and its walk, instances, the scene in memory,
** the queues and the scheduler's loop (and schedule_reference, the same
** loop in one function), the geometry cache.  The loop calls batchrt's
** layers (Part II) through hooks declared after the scheduler's types.
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

/* partition, batch_range: internal.h (the build cuts points with them) */

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
** holds at most point_tris triangles.  The split point is a multiple of
** point_tris near the middle, so parts are full and there are few of them
** (ceil(n / point_tris) when the counts allow). */
brt_result brt_partition_split(partition *p, const float *centroids, uint32_t first,
                                  uint32_t count, uint32_t point_tris)
{
    uint32_t parts, k;
    brt_result r;
    if (count <= point_tris) return partition_push(p, first, count);
    parts = (uint32_t)(((uint64_t)count + point_tris - 1) / point_tris);
    k = (uint32_t)(((uint64_t)parts / 2) * point_tris);
    median_split(centroids, p->order + first, count, k);
    /* Both sides are smaller and k is near the middle: depth O(log n). */
    r = brt_partition_split(p, centroids, first, k, point_tris);
    if (r == BRT_OK) r = brt_partition_split(p, centroids, first + k, count - k, point_tris);
    return r;
}

/* Instances are partitioned the same way, by the centres of their world
** boxes, but a batching point's size is what its load reads: the
** triangles of the distinct prototypes it references, each counted once,
** as pandora counts them.  A range is split at its median while it is
** larger than point_tris and references more than one prototype: a
** prototype larger than point_tris then gets points of its own instances,
** its blob shared by them all and cached once (splitting the prototype
** into pieces, as pandora does, would save no bytes: each piece would
** still be read whole).  Optionally (brt_scene_options.point_instanced)
** a range is split too while its instances hold more triangles than that,
** which gives points of the paper's sizes (10-25 M instanced triangles)
** whatever the prototypes.  size_of(user, ids, n, &distinct, &instanced)
** measures a range. */
/* range_size_fn, size_limits: internal.h */

brt_result brt_partition_by_size(partition *p, const float *centres, uint32_t first,
                                    uint32_t count, const size_limits *limits,
                                    range_size_fn size_of, void *user)
{
    uint32_t distinct, k = count / 2;
    uint64_t instanced, unique;
    brt_result r;
    if (count <= 1) return partition_push(p, first, count);
    unique = size_of(user, p->order + first, count, &distinct, &instanced);
    if ((unique <= limits->point_tris || distinct <= 1) &&
        (limits->point_instanced == 0 || instanced <= limits->point_instanced))
        return partition_push(p, first, count);
    median_split(centres, p->order + first, count, k);
    r = brt_partition_by_size(p, centres, first, k, limits, size_of, user);
    if (r == BRT_OK) r = brt_partition_by_size(p, centres, first + k, count - k, limits, size_of, user);
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
** top-level section (TOP_NODE_BYTES) and checked at open against the point
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
/* top_node, TOP_EMPTY, TOP_LEAF, TOP_NODE_BYTES: internal.h (the scene
** file stores the nodes) */

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

void brt_top_lane_clear(top_node *node, int lane)
{
    int a;
    node->child[lane] = TOP_EMPTY;
    for (a = 0; a < 3; a++) {
        node->box[a][lane] = INFINITY;
        node->box[3 + a][lane] = -INFINITY;
    }
}

void brt_top_lane_grow(top_node *node, int lane, const float *box)
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
    for (g = 0; g < 4; g++) brt_top_lane_clear(&b->nodes[index], (int)g);
    for (g = 0; g < groups; g++) {
        uint32_t size = first[g + 1] - first[g];
        uint32_t child = size == 1 ? (TOP_LEAF | ids[first[g]])
                                   : top_build_node(b, ids + first[g], size);
        b->nodes[index].child[g] = child;
        for (i = first[g]; i < first[g + 1]; i++)
            brt_top_lane_grow(&b->nodes[index], (int)g, b->boxes + 6 * (size_t)ids[i]);
    }
    return index;
}

/* Builds the nodes (at most count of them: every node has two or more
** children, except a root over a single batching point). */
brt_result brt_top_build(const float *boxes, uint32_t count, top_node **nodes,
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
** batching points (brt_top_build, over their world boxes), descended here
** depth first, nearest child first, and pruned by the closest hit so far.
** Its boxes are tested grown by the margin of bvh.c ("Instances"), so the
** rounding of the ray's transform never prunes a hit.  direct mode (a
** brt_world) and batched mode intersect through the same function,
** brt_intersect_ray (closest hit or, for an occlusion ray, any hit), so they
** write the same bytes.
*/
static void hit_mark_occluded(brt_hit *hit);

/* instance_margin (the margin of a box of instances): internal.h */

static float margin_of(const instance_margin *m, const brt_ray *ray)
{
    return brt_instance_margin(m->condition, m->reach, m->center, ray);
}

/* Starts a margin about the centre of the box lo..hi (no instances yet). */
void brt_margin_begin(instance_margin *m, const float lo[3], const float hi[3])
{
    int a;
    m->condition = m->reach = 0.0f;
    for (a = 0; a < 3; a++) m->center[a] = 0.5f * lo[a] + 0.5f * hi[a];
}

/* Takes in an instance: its frame and its radius. */
void brt_margin_add(instance_margin *m, const brt_instance_frame *f, float radius)
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

/* instance_set, geometry, INSTANCE_DILATION, SET_STACK: internal.h (the
** scene file, the world and the scheduler share them) */

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
void brt_intersect_ray(const geometry *g, const brt_ray *ray, uint64_t tag, brt_hit *hit,
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
brt_result brt_instance_admit(const brt_instance *in, uint32_t number, uint32_t prototypes,
                                 brt_instance_frame *frame, brt_error *err)
{
    if (in->prototype >= prototypes)
        return brt_fail(err, BRT_EARG, "instance %u: prototype %u out of range (%u prototypes)",
                        (unsigned)number, (unsigned)in->prototype, (unsigned)prototypes);
    return brt_instance_frame_init(in, number, frame, err);
}

/* Builds the box tree over a set's instances, whose world boxes are
** boxes[6i..6i+5] (lo, hi). */
brt_result brt_set_build_tree(instance_set *set, const float *boxes)
{
    uint32_t i;
    set->nodes = NULL;
    set->node_count = 0;
    if (set->count == 0) return BRT_OK;
    if (brt_top_build(boxes, set->count, &set->nodes, &set->node_count) != BRT_OK) return BRT_ENOMEM;
    for (i = 0; i < set->node_count; i++) brt_top_node_pad(&set->nodes[i]);
    return BRT_OK;
}

/* The set's margin, about the centre of its instances' boxes. */
void brt_set_fit_margin(instance_set *set, const float *boxes, const float *radii)
{
    float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    uint32_t i;
    int a;
    for (i = 0; i < set->count; i++)
        for (a = 0; a < 3; a++) {
            if (boxes[6 * (size_t)i + a] < lo[a]) lo[a] = boxes[6 * (size_t)i + a];
            if (boxes[6 * (size_t)i + 3 + a] > hi[a]) hi[a] = boxes[6 * (size_t)i + 3 + a];
        }
    brt_margin_begin(&set->margin, lo, hi);
    for (i = 0; i < set->count; i++) brt_margin_add(&set->margin, &set->frames[i], radii[i]);
}

void brt_set_free(instance_set *set)
{
    if (set->mapping) {
        munmap(set->mapping, set->mapping_bytes);
    } else {
        free(set->uses);
        free(set->ids);
        free(set->prototypes);
        free(set->frames);
        free(set->nodes);
    }
    memset(set, 0, sizeof *set);
}

/* ---- the scene in memory ---------------------------------------------- */
/*
** What the scheduler works on.  An open scene (struct brt_scene) holds the
** scene file's small parts in memory -- per batching point its box, blob
** place and proxies (point_entry), the top-level nodes, the DAG pool --
** and leaves the blobs on disk.  The geometry cache keeps some blobs
** resident (cache_entry per batching point).  The code that fills these
** structures is in scene.c (the scene file).
*/
/* point_entry, proto_entry, section, scene_header, blob_view: internal.h */

/* One blob while a trace runs -- a batching point's or a prototype's --
** and the geometry cache's state for it (SQLite's pcache shape: fetch
** pins, release unpins, only unpinned entries are evicted, least recently
** used first). */
typedef struct cache_entry {
    void *data;                 /* page-aligned copy of the blob, or NULL */
    blob_view view;             /* into data */
    geometry geometry;          /* a batching point's, for brt_intersect_ray */
    uint64_t bytes;             /* what data holds (page-rounded) and the
                                ** resident layout decoded of it (decoded) */
    uint64_t decoded;
    uint32_t pins;
    uint32_t lru_prev, lru_next;   /* unpinned resident entries; NO_ENTRY ends */
} cache_entry;

#define NO_ENTRY 0xFFFFFFFFu

/* blob_place and struct brt_scene: internal.h */

typedef struct geometry_cache {
    brt_scene *scene;
    cache_entry *entries;       /* per blob: batching points, then prototypes */
    uint32_t entry_count;
    const brt_bvh **prototypes; /* per prototype: its BVH while resident, else NULL */
    uint32_t working_set;       /* blobs the last fetch needed (cache_check) */
    uint64_t budget, held;
    uint64_t all_bytes;         /* cache_bytes of every blob at once */
    uint64_t decoded;           /* resident layouts held (layer 8) */
    int decode;                 /* layer 8 on (not no_decode) */
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

/* The geometry cache's interface: its section follows the scheduler's. */
static brt_result cache_init(geometry_cache *c, brt_scene *scene, uint64_t budget,
                             const brt_trace_options *opt, brt_stats *stats);
static void cache_free(geometry_cache *c);
static brt_result cache_fetch(geometry_cache *c, uint32_t id, const geometry **g, brt_error *err);
static const geometry *cache_peek(const geometry_cache *c, uint32_t id);
static void cache_touch(geometry_cache *c, uint32_t id);
static void cache_release(geometry_cache *c, uint32_t id);
static void cache_release_blob(geometry_cache *c, uint32_t id);
static brt_result cache_check(const geometry_cache *c, brt_error *err);
static brt_result blob_read(const geometry_cache *c, uint32_t id, uint64_t *bytes_read, void **data,
                            blob_view *view, brt_error *err);
static void view_free(blob_view *view);
static void blob_free(const brt_scene *scene, uint32_t id, void *data);
static uint64_t cache_bytes(const brt_scene *scene, uint32_t id);

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
** command measures it.  They are numbered in the order of the data flow
** (the set-up, a ray's walk, settling it, the loads, a batch's
** intersections, the threads), one section each in Part II; their hooks
** are declared after these types.
**   1. proxies_pay         no proxy tests when the budget holds every blob
**   2. rays_in_flight      in core: few rays in flight by default
**   3. inner_stops         inner proxies: an occlusion ray settled occluded
**                          without a queue (the paper's future work)
**   4. intersect_resident  geometry in memory: intersect at once, no queue
**   5. exact_proxy_hit     analysis: the triangles themselves as the proxy
**   6. forward, take_rays  other processes (brt_exchange): a ray stopping
**                          at a point owned elsewhere is sent there, and
**                          rays sent here are queued where they stopped
**   7. fetch_for           statistics: the loads only occlusion rays asked
**                          for
**   8. cache_decode        in core: a point loaded is decoded to float
**                          nodes when the budget holds it beside every blob
**   9. cache_read_ahead    threads: the next load read while a phase runs
**  10. clip_to_entry       a queued ray's BVH walk starts where it entered
**                          the proxy (the paper's future work)
**  11. order_batch         a batch's rays intersected in the order of the
**                          voxels where they entered the proxy (the same)
**  12. phases_run          threads: the loop's rays walked in parallel and
**                          settled in order
** paper_scheduler turns layers 1 and 4 off (what make figures measures as
** the paper's scheduler); exact_proxies turns 5 on; one thread turns 9
** and 12 off; no_inner turns 3 off; no_decode turns 8 off; no_clip and
** no_order turn 10 and 11 off (and so do proxies off: no entry is known).
** No layer changes a hit; 1 and 3-5 change which loads happen, 2 and
** 7-12 none (the threads: tests hold the phases byte-equal to the plain
** loop), and 6 shares the loads among processes, each loading the points
** it owns.
**
** Rays in flight live in slots; a queue per batching point holds slot
** numbers; a min-heap of queue keys (key_heap) orders the non-empty
** queues, longest first, ties to the lowest id.
**
** Per-ray state while queued (ray_slot, 96 bytes): the ray, its closest
** hit so far and that triangle's normal, its walk key, the number of
** batching points it was queued at, where it entered the proxy that
** admitted it (layers 10 and 11) and the caller's tag.  The tag also says
** the ray's kind (BRT_TAG_OCCLUSION), so an occlusion ray costs no byte
** more: it keeps an unused normal, and its hit record turns from the miss
** record into "occluded" at its first hit.
*/
typedef struct ray_slot {
    brt_ray ray;
    brt_hit hit;
    float normal[3];
    walk_key key;
    uint32_t visits;
    float entry_t;              /* the proxy cast's entry, rounded down
                                ** (brt_proxy_raycast), kept by proxy_test
                                ** when it admits the ray (layers 10-11 read
                                ** it then alone); tnear for a ray received */
    uint32_t entry_voxel;       /* the Morton code of the voxel there */
    uint64_t tag;
} ray_slot;

/* The README's size of a waiting ray ("A ray's state"), where a uint64_t
** is aligned to 8. */
typedef char ray_slot_is_96_bytes[sizeof(ray_slot) == 96 || sizeof(void *) < 8 ? 1 : -1];

typedef struct ray_queue {
    uint32_t *slots;
    uint32_t count;
    size_t capacity;
} ray_queue;

/* The threaded variant's state and its record of the resident batching
** points a walk used: Part II, layer 12. */
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
    int clip, order;            /* layers 10 and 11 (not no_clip, no_order) */
    int proxies_in_core;        /* brt_trace_options.proxies_in_core */
    brt_stats *stats;
    geometry_cache cache;
    ray_slot *slots;
    uint32_t *free_slots, free_count, capacity;
    ray_queue *queues;
    key_heap fullest;                       /* the non-empty queues (queue_key) */
    walker walker;                          /* the plain loop's walk */
    phase_threads *threads;                 /* layers 9, 12; NULL: one thread */
    geometry *exact;                        /* exact_proxies: every point's, or NULL */
    blob_view *exact_views;                 /* every blob's, opened */
    void **exact_data;
    const brt_bvh **exact_prototypes;
    brt_ray *incoming;
    uint64_t *incoming_tags;
    uint32_t *fresh;                        /* the slots refill just filled */
    uint64_t *order_items, *order_spare;    /* layer 11's sort, or NULL */
    uint32_t *order_slots;                  /* a batch in layer 11's order */
    const brt_trace_options *follow;        /* trace --follow: steps reported, or NULL */
    const volatile sig_atomic_t *interrupt; /* brt_trace_options.interrupt */
    uint64_t fetch_bytes;                   /* bytes the last fetch read (its step) */
    const brt_exchange *exchange;           /* layer 6, or NULL */
    brt_ray_state *arrivals;                /* rays received (layer 6) */
} scheduler;

/* The layers' hooks, as the loop calls them (Part II), in layer order;
** each is defined in its layer's section. */
/* 1-2, the set-up (scheduler_init) */
static int proxies_pay(const scheduler *s, uint64_t budget);
static uint32_t rays_in_flight(const brt_trace_options *opt, uint64_t budget, uint64_t every_blob);
/* 3-5, a ray's walk (walk_on, proxy_test, enqueue; trace_source reads 5's BVHs) */
static int inner_stops(const scheduler *s, ray_slot *r);
static int intersect_resident(const scheduler *s, walker *w, ray_slot *r, const prepared_ray *p,
                              float tlimit);
static int proxy_admits(const scheduler *s, uint32_t id, const brt_ray *ray, float tlimit, float *t);
static brt_result exact_load(scheduler *s, brt_error *err);
/* 6, settling a ray and taking rays (settle, refill, queues_waiting) */
static int owned_elsewhere(const scheduler *s, uint32_t id);
static brt_result forward(scheduler *s, uint32_t slot);
static size_t take_rays(scheduler *s, int idle, brt_result *res, brt_error *err);
/* 7, a queue's load (process_batch) */
static brt_result fetch_for(scheduler *s, uint32_t id, const ray_queue *q, const geometry **g,
                            brt_error *err);
/* 8-9, the cache's load (cache_load; cache_free drops a blob read ahead) */
static uint64_t cache_decode(geometry_cache *c, cache_entry *e);
static int cache_ahead_take(geometry_cache *c, uint32_t id);
static void cache_ahead_drop(geometry_cache *c);
/* 10-11, a batch's intersections (proxy_test keeps the entry; run_rays
** and phases_run intersect) */
static void entry_keep(const scheduler *s, ray_slot *r, float t);
static const brt_ray *clip_to_entry(const scheduler *s, const ray_slot *r, brt_ray *clipped);
static brt_result order_init(scheduler *s);
static const uint32_t *order_batch(scheduler *s, const uint32_t *slots, uint32_t count);
/* 12, the threads (run_rays, scheduler_init, scheduler_free; walker_used
** logs a walk's uses) */
static brt_result phases_run(scheduler *s, const uint32_t *slots, uint32_t count, uint32_t id,
                             const geometry *g, const uint32_t *order);
static brt_result threads_init(scheduler *s, unsigned threads);
static void threads_free(scheduler *s);
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

/* ---- a ray's walk: intersect at once, or the proxy test and a queue -- */

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
** brt_ray_source: t = 0, prim = 0 when occluded).  ray is the slot's, or
** the same with a later tnear (layer 10). */
static void intersect_slot(const scheduler *s, const geometry *g, ray_slot *r, const brt_ray *ray,
                           const prepared_ray *p)
{
    brt_intersect_ray(g, ray, r->tag, &r->hit, r->normal, p);
    follow_step(s, r, BRT_STEP_TRIANGLES, r->key.id, r->hit.t);
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
    const point_entry *b = &scene->points[id];
    if (b->instances && !(margin_of(&b->margin, ray) <= INSTANCE_DILATION * b->proxy.cell)) {
        if (t) *t = ray->tnear;
        return 1;
    }
    return brt_proxy_raycast(scene->dag, &b->proxy, ray, ray->tnear, tlimit, t);
}

/* The paper's proxy test at the batching point where the walk stands: a
** miss culls the visit (no queue, no load).  With proxies off (no_proxy,
** or layer 1) every batching point reached is queued, as in Pharr et al.
** A ray admitted keeps where it entered the proxy (layers 10 and 11). */
static int proxy_test(const scheduler *s, walker *w, ray_slot *r, float tlimit)
{
    const int keep = s->clip || s->order;
    float t = r->key.t;
    int hit;
    if (!s->use_proxies) return 1;
    w->proxy_tests++;
    hit = proxy_admits(s, r->key.id, &r->ray, tlimit, s->follow || keep ? &t : NULL);
    w->proxy_culled += !hit;
    follow_step(s, r, hit ? BRT_STEP_PROXY_HIT : BRT_STEP_PROXY_MISS, r->key.id, t);
    if (hit && keep) entry_keep(s, r, t);                   /* layers 10-11 */
    return hit;
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
        if (inner_stops(s, r)) {                            /* layer 3 */
            w->inner_stopped++;
            break;
        }
        if (intersect_resident(s, w, r, margin == 0.0f ? &p : NULL, tlimit)) {   /* layer 4 */
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

/* ---- settling a ray, and the scheduler's loop ------------------------ */

/* A ray whose walk stopped: queued at batching point id (or sent to the
** process owning it: layer 6), or, when id is NO_ENTRY, finished (the
** source hears of it; its slot is free). */
static brt_result settle(scheduler *s, uint32_t slot, uint32_t id)
{
    ray_slot *r = &s->slots[slot];
    if (id != NO_ENTRY) return owned_elsewhere(s, id) ? forward(s, slot) : enqueue(s, id, slot);
    s->stats->occlusion_hits += found_occluder(r);
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
    s->stats->occlusion_inner_stopped += w->inner_stopped;
    w->resident_visits = w->proxy_tests = w->proxy_culled = w->inner_stopped = 0;
}

/* The hooks of a batch's intersections (testing.h), compiled in with
** BRT_TESTING only. */
#ifdef BRT_TESTING
static brt_test_batch_fn test_batch_fn;
static void *test_batch_user;
static int test_counting;      /* brt_test_count_bottom */
static uint64_t test_bottom_rays, test_bottom_nodes, test_nodes_before;
static double test_bottom_seconds, test_seconds_before;
void brt_test_count_bottom(int on)
{
    test_counting = on != 0;
    brt_test_count_nodes(on);
}
void brt_test_on_batch_ray(brt_test_batch_fn fn, void *user)
{
    test_batch_fn = fn;
    test_batch_user = user;
}
void brt_test_bottom_level(uint64_t *rays, uint64_t *nodes, double *seconds)
{
    *rays = test_bottom_rays;
    *nodes = test_bottom_nodes;
    *seconds = test_bottom_seconds;
}
#define TEST_BATCH_RAY(id, place, r, walked) \
    do { if (test_batch_fn) test_batch_fn(test_batch_user, id, place, (r)->tag, walked, (r)->entry_voxel); } while (0)
#define TEST_BOTTOM_BEGIN() \
    do { if (test_counting) { test_nodes_before = brt_test_node_visits(); test_seconds_before = brt_seconds(); } \
    } while (0)
#define TEST_BOTTOM_END(count) \
    do { if (test_counting) { test_bottom_rays += (count); \
             test_bottom_nodes += brt_test_node_visits() - test_nodes_before; \
             test_bottom_seconds += brt_seconds() - test_seconds_before; } } while (0)
#else
#define TEST_BATCH_RAY(id, place, r, walked) ((void)0)
#define TEST_BOTTOM_BEGIN() ((void)0)
#define TEST_BOTTOM_END(count) ((void)0)
#endif

/* The rays of slots[0..count): first intersected at batching point id
** (its geometry g; id is NO_ENTRY for new rays), then each walks on and is
** settled.
** Releasing the point before the walks makes its place in the LRU order
** come before the points the walks use (no ray of its queue enters it
** again: walk keys only grow).  With threads, layer 12 does the same in
** phases. */
static brt_result run_rays(scheduler *s, const uint32_t *slots, uint32_t count, uint32_t id,
                           const geometry *g)
{
    brt_result r = BRT_OK;
    uint32_t i;
    if (s->threads)                                                 /* layer 12 */
        return phases_run(s, slots, count, id, g, id != NO_ENTRY ? order_batch(s, slots, count) : NULL);
    if (id != NO_ENTRY) {
        const uint32_t *order = order_batch(s, slots, count);       /* layer 11 */
        TEST_BOTTOM_BEGIN();
        for (i = 0; i < count; i++) {
            ray_slot *ray = &s->slots[order[i]];
            brt_ray clipped;
            const brt_ray *walked = clip_to_entry(s, ray, &clipped);          /* layer 10 */
            TEST_BATCH_RAY(id, i, ray, walked);
            intersect_slot(s, g, ray, walked, NULL);
        }
        TEST_BOTTOM_END(count);
        cache_release(&s->cache, id);
    }
    for (i = 0; i < count && r == BRT_OK; i++)
        r = settle(s, slots[i], walk_on(s, &s->walker, &s->slots[slots[i]]));
    walker_count(s, &s->walker);
    return r;
}

/* Why settling rays failed: a full memory, or an exchange that could
** not send (layer 6). */
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
    r->entry_t = ray->tnear;    /* no proxy entered yet: every field defined */
    r->entry_voxel = 0;
    r->key.t = -INFINITY;
    r->key.id = TOP_EMPTY;
    stats->rays++;
    stats->occlusion_rays += is_occlusion(r);
}

/* Takes the rays other processes sent (layer 6), then new rays from the
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
** rays here: wait for them (layer 6; at once false without an exchange). */
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

/* capacity_hint: the number of rays there will be, when known (0: not),
** so that 20 rays do not get a million slots. */
static brt_result scheduler_init(scheduler *s, brt_scene *scene, const brt_trace_options *opt,
                                 const brt_ray_source *source, size_t capacity_hint,
                                 brt_stats *stats)
{
    uint32_t n = scene->header.point_count, i;
    uint64_t budget = opt && opt->memory_limit ? opt->memory_limit : UINT64_MAX;
    memset(s, 0, sizeof *s);
    s->scene = scene;
    s->source = source;
    s->stats = stats;
    s->use_proxies = !(opt && opt->no_proxy);
    s->paper_scheduler = opt && opt->paper_scheduler;
    s->use_inner = !(opt && opt->no_inner);
    s->clip = !(opt && opt->no_clip);
    s->order = !(opt && opt->no_order);
    s->proxies_in_core = opt && opt->proxies_in_core;
    s->follow = opt && opt->follow ? opt : NULL;
    s->interrupt = opt ? opt->interrupt : NULL;
    s->exchange = opt ? opt->exchange : NULL;
    /* With proxies on, they take their bytes from the same budget (the
    ** paper's Fig. 3 lowers the geometry limit by the proxies' memory). */
    stats->proxy_bytes = s->use_proxies ? brt_svdag_memory_bytes(scene->dag) : 0;
    if (budget != UINT64_MAX) budget = budget > stats->proxy_bytes ? budget - stats->proxy_bytes : 0;
    if (cache_init(&s->cache, scene, budget, opt, stats) != BRT_OK) return BRT_ENOMEM;
    if (!proxies_pay(s, budget)) s->use_proxies = 0;            /* layer 1 */
    if (!s->use_proxies) s->clip = s->order = 0;                /* no entries to use */
    s->capacity = rays_in_flight(opt, budget, s->cache.all_bytes);   /* layer 2 */
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
        (s->order && order_init(s) != BRT_OK) ||
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
    for (i = 0; s->queues && i < s->scene->header.point_count; i++) free(s->queues[i].slots);
    cache_free(&s->cache);
    free(s->slots);
    free(s->free_slots);
    free(s->queues);
    free(s->fullest.keys);
    free(s->fullest.pos);
    free(s->incoming);
    free(s->incoming_tags);
    free(s->fresh);
    free(s->order_items);
    free(s->order_spare);
    free(s->order_slots);
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

/* ---- the paper's loop, plain (schedule_reference) --------------------- */
/*
** The scheduler's loop with every layer off -- one thread,
** paper_scheduler, no_inner, no_decode, no exchange -- as one function
** to be read top to bottom, as pbrt-v4's BVHAggregate::Intersect reads:
** rays walk the top-level BVH; at each batching point whose proxy admits
** a ray (cast up to its closest hit so far) the ray is queued and stops;
** when no ray can move, the fullest queue is served -- its blob (and a
** point of instances' prototypes) pinned in the LRU geometry cache, its
** rays intersected, the blobs released -- and each of its rays walks on
** from where it stopped; until every ray has finished.  It shares only
** the plain parts: the top-level walk, proxy_cast, blob_read,
** brt_intersect_ray, and geometry_cache as a table of blobs (not cache_fetch,
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
    const uint32_t points = c->scene->header.point_count;
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
    const uint32_t points = scene->header.point_count;
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
                stats->occlusion_hits += found_occluder(ray);
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
            brt_intersect_ray(&c.entries[best].geometry, &ray->ray, ray->tag, &ray->hit, ray->normal, NULL);
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
    uint64_t bytes = brt_round_up_page(scene->blobs[id].size);
    return bytes ? (size_t)bytes : SCENE_PAGE;
}

static void blob_free(const brt_scene *scene, uint32_t id, void *data)
{
    if (data) munmap(data, blob_buffer_bytes(scene, id));
}

/* What blob id costs the budget: its page-rounded buffer, and for a point
** of instances what brt_instance_table_open allocates beside it, bounded from
** its table entry (a frame, two numbers and at most one tree node per
** instance, a prototype number per distinct prototype), so that the limit
** bounds the resident bytes. */
static uint64_t cache_bytes(const brt_scene *scene, uint32_t id)
{
    uint64_t bytes = brt_round_up_page(scene->blobs[id].size);
    if (id < scene->header.point_count && scene->points[id].instances)
        bytes += (uint64_t)scene->points[id].instances *
                 (sizeof(brt_instance_frame) + 3 * sizeof(uint32_t) + sizeof(top_node));
    return bytes;
}

/* What the cache would hold with every blob in memory at once. */
static uint64_t all_cache_bytes(const brt_scene *scene)
{
    const uint32_t n = scene->header.point_count + scene->header.prototype_count;
    uint64_t bytes = 0;
    uint32_t i;
    for (i = 0; i < n; i++) bytes += cache_bytes(scene, i);
    return bytes;
}

static void view_free(blob_view *view)
{
    brt_bvh_free(view->bvh);
    if (view->set) brt_set_free(view->set);
    free(view->set);
    view->bvh = NULL;
    view->set = NULL;
}

/* Entry id's blob is a prototype's: its BVH leaves or joins the table. */
static void cache_note_prototype(geometry_cache *c, uint32_t id)
{
    const uint32_t b = c->scene->header.point_count;
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
    uint32_t i, n = scene->header.point_count + scene->header.prototype_count;
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
    c->read_fn = opt && opt->read_fn ? opt->read_fn : brt_pread_reader;
    c->read_user = opt ? opt->read_user : NULL;
    c->drop_os_cache = opt && opt->drop_os_cache;
    c->decode = !(opt && opt->no_decode);
    c->all_bytes = all_cache_bytes(scene);
    c->stats = stats;
    return BRT_OK;
}

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
** check_points); a point of instances' table by brt_instance_table_open; a
** prototype's BVH against its own triangle count. */
static brt_result check_blob(const brt_scene *s, uint32_t id, const void *data, blob_view *view,
                             brt_error *err)
{
    const uint32_t b = s->header.point_count;
    const uint32_t expect = id < b ? s->points[id].triangles : s->prototypes[id - b].triangles;
    brt_error why;
    uint32_t held;
    view->bvh = NULL;
    view->set = NULL;
    if (id < b && s->points[id].instances)
        return brt_instance_table_open(s, id, data, s->blobs[id].size, &view->set, err);
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
    uint64_t bytes = brt_round_up_page(b->size), done = 0;
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
        r = brt_read_fully(c->scene->fd, (unsigned char *)*data + done, chunk, b->offset + done,
                       c->read_fn, c->read_user, bytes_read, c->scene->path, err);
        done += chunk;
    }
    if (c->drop_os_cache) posix_fadvise(c->scene->fd, (off_t)b->offset, (off_t)bytes, POSIX_FADV_DONTNEED);
    if (r == BRT_OK && brt_checksum64(*data, b->size) != b->checksum)
        r = brt_fail(err, BRT_EFORMAT, "%s: %s %u: checksum mismatch (corrupt file)", c->scene->path,
                     id < c->scene->header.point_count ? "batching point" : "prototype",
                     id < c->scene->header.point_count ? id : id - c->scene->header.point_count);
    if (r == BRT_OK) r = check_blob(c->scene, id, *data, view, err);
    if (r != BRT_OK) {
        blob_free(c->scene, id, *data);
        *data = NULL;
    }
    return r;
}

/* ---- loading a blob (layer 8 decodes it), pinning, releasing -------- */

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
    e->decoded = cache_decode(c, e);                        /* layer 8 */
    c->stats->load_seconds += brt_seconds() - start;
    e->geometry.triangles = e->view.bvh;
    e->geometry.instances = e->view.set;
    e->geometry.prototypes = c->prototypes;
    cache_note_prototype(c, id);
    e->bytes = bytes + e->decoded;
    c->held += e->bytes;
    if (id < c->scene->header.point_count) c->stats->batch_loads++;
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
        if ((r = cache_pin(c, c->scene->header.point_count + set->uses[k], err)) != BRT_OK) {
            while (k-- > 0) cache_release_blob(c, c->scene->header.point_count + set->uses[k]);
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
    for (k = 0; set && k < set->use_count; k++) fn(c, c->scene->header.point_count + set->uses[k]);
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
/* PART II -- BATCHRT'S LAYERS                                           */
/* ##################################################################### */
/*
** batchrt's departures from the paper's loop, each a named function that
** the loop of Part I calls through its hooks (declared there in this
** order) and none changing a hit: one section a layer, numbered in the
** order of the data flow -- the set-up (1-2), a ray's walk (3-5),
** settling it (6), a queue's load (7), the cache's load (8-9), a batch's
** intersections (10-11), the threads (12) -- as in the README's table
** ("The scheduler, and where batchrt departs from the paper"), which says
** what turns each off.  Each section's first comment is the layer's
** design: why it is there and which command measures it.
*/

/* ---- layer 1: proxies off when everything fits (proxies_pay) ---- */

/* Layer 1, proxies off when everything fits: proxies only spare loads.
** When the budget (what is left of it after the proxies) holds every
** blob nothing is ever evicted, so a load a proxy spares is only put off
** -- unless no ray ever needs that batching point -- while every test
** costs a cast.  So the default scheduler does not consult them then;
** the paper's (paper_scheduler) does, and so does a trace over several
** processes (layer 6), where a proxy miss also spares a message.  The
** paper's open question -- would a proxy test pay in core, before each
** intersection at a point in memory, culling some and clipping the rest
** (layer 10)? -- is answered by make bench-order's last column
** (proxies_in_core against this layer): on every scene and ray kind it
** measures the casts cost more time than the BVH nodes they spare, so the
** proxies stay off, and proxies_in_core is there to measure it again.
** Every blob: the batching points' and the prototypes', as the cache
** charges them (its all_bytes). */
static int proxies_pay(const scheduler *s, uint64_t budget)
{
    return s->paper_scheduler || s->exchange || s->proxies_in_core || budget < s->cache.all_bytes;
}

/* ---- layer 2: few rays in flight in core (rays_in_flight) ---- */

/* Layer 2, few rays in flight in core.  Rays in flight are there to
** gather rays at a batching point before its load.  When the budget holds
** every blob no point is ever loaded twice, so gathering spares no load,
** while a million waiting rays (a ray_slot each) push each other and the
** BVHs out of the processor's caches.  The default is then IN_CORE_RAYS
** (make bench-embree's batched column runs with it; trace --batched
** --rays-in-flight N --stats on the same rays times any other number).
** Not with an exchange (layer 6), whose messages the waiting rays fill. */

static uint32_t rays_in_flight(const brt_trace_options *opt, uint64_t budget, uint64_t every_blob)
{
    if (opt && opt->rays_in_flight) return opt->rays_in_flight;
    if (!(opt && opt->exchange) && budget >= every_blob) return IN_CORE_RAYS;
    return OUT_OF_CORE_RAYS;
}

/* ---- layer 3: inner proxies (inner_stops) ---- */

/* Layer 3, inner proxies: the inner proxy test, first at every batching
** point an occlusion ray with tfar = +inf reaches: a hit settles the ray
** occluded (the record of intersect_slot) with no queue and no load.
** make bench-inner prints how many rays it settles and the disk bytes
** read with and without it. */
static int inner_stops(const scheduler *s, ray_slot *r)
{
    if (!s->use_inner || !is_occlusion(r)) return 0;   /* the cast refuses tfar < inf */
    if (!brt_inner_occludes(s->scene->dag, &s->scene->points[r->key.id].inner, &r->ray)) return 0;
    hit_mark_occluded(&r->hit);
    follow_step(s, r, BRT_STEP_INNER, r->key.id, r->key.t);
    return 1;
}

/* ---- layer 4: intersecting at once in memory (intersect_resident) ---- */

/* A resident batching point was just used: the LRU order hears of it. */
static void walker_used(walker *w, uint32_t id)
{
    if (w->cache) cache_touch(w->cache, id);
    else use_log_record(w->uses, id);                       /* layer 12 */
}

/* Layer 4, intersecting at once in memory: at a batching point whose
** geometry is resident (and unless paper_scheduler asks for the paper's
** plain scheduler) the ray needs no queue: it is intersected there at
** once and walks on.  Its proxy is not consulted: the BVH answers exactly
** at about the cost of a proxy cast.  Why it matters: a bounce ray starts
** inside the batching point just processed, still in memory; queued, it
** would wait there until that point might be evicted and read again.
** make figures writes the loads and disk bytes with and without it
** (fig3.csv: the paper's scheduler, --paper-scheduler, beside batchrt's).
** With proxies_in_core the proxy is asked first after all: a miss spares
** the BVH, a hit clips it (layer 10); make bench-order's in-core table
** says whether that pays (README, "Proxies in core").  Returns 0 when the
** point is not resident.  p serves the clipped ray too: the BVH walk
** reads tnear from the ray, not from its preparation. */
static int intersect_resident(const scheduler *s, walker *w, ray_slot *r, const prepared_ray *p,
                              float tlimit)
{
    const geometry *resident = s->paper_scheduler ? NULL : cache_peek(&s->cache, r->key.id);
    brt_ray clipped;
    if (!resident) return 0;
    walker_used(w, r->key.id);
    if (s->proxies_in_core && !proxy_test(s, w, r, tlimit)) return 1;   /* culled */
    follow_step(s, r, BRT_STEP_RESIDENT, r->key.id, r->key.t);
    r->visits++;
    w->resident_visits++;
    intersect_slot(s, resident, r, s->proxies_in_core ? clip_to_entry(s, r, &clipped) : &r->ray, p);
    return 1;
}

/* ---- layer 5: exact proxies, for analysis (exact_proxy_hit) ---- */

/* Layer 5, exact proxies (exact_proxies; analysis, not a way to trace):
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
    brt_intersect_ray(&s->exact[id], &segment, BRT_TAG_OCCLUSION, &hit, NULL, NULL);
    return hit.t == 0.0f;
}

/* The paper's proxy question (proxy_cast), or layer 5's exact answer
** (*t: tnear then). */
static int proxy_admits(const scheduler *s, uint32_t id, const brt_ray *ray, float tlimit, float *t)
{
    if (s->exact) {
        if (t) *t = ray->tnear;
        return exact_proxy_hit(s, id, ray, tlimit);
    }
    return proxy_cast(s->scene, id, ray, tlimit, t);
}

/* Layer 5's set-up (exact_proxies): every batching point's BVH, read
** once, outside the cache and its statistics (exact_proxy_hit). */
static brt_result exact_load(scheduler *s, brt_error *err)
{
    const uint32_t b = s->scene->header.point_count, n = s->cache.entry_count;
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

/* ---- layer 6: batching points owned by other processes (forward, take_rays) ---- */

/* Layer 6, other processes (brt_trace_options.exchange; README, "Beyond
** one machine"): each holds the top-level BVH and every proxy, and owns
** the batching points brt_scene_assign gives it (below), whose blobs alone
** it reads.  A walk that stops at a point owned elsewhere, after its proxy
** admitted the ray, sends the ray there with its whole state (forward);
** rays sent here are queued where they stopped (take_rays).  A proxy miss
** spares a message as it spares a load, so the proxies are always
** consulted (layer 1).  make bench-mpi prints the rays sent, messages and
** loads per run, with proxies and without. */
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
    r->entry_t = r->ray.tnear;  /* the sender's proxy entry does not travel */
    r->entry_voxel = 0;
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

/* Queues rays sent here by other processes at the points they stopped at
** (their proxies admitted them there): waits for them when idle.  Returns
** how many came; 0 with idle means every process is done. */
static size_t take_rays(scheduler *s, int idle, brt_result *res, brt_error *err)
{
    const uint32_t points = s->scene->header.point_count;
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

/* The owners of batching points (brt_scene_assign): runs of the top-level
** BVH's leaf order balanced by the bytes a load reads, or round robin. */

/* What a load of point id reads: its blob (cache_bytes) and, for a point
** of instances, its triangles' share of the prototypes' bytes -- an
** estimate: which prototypes it uses is in its blob, on disk. */
static double point_weight(const brt_scene *s, uint32_t id)
{
    double bytes = (double)cache_bytes(s, id), proto_bytes = 0.0, proto_tris = 0.0;
    uint32_t i;
    if (!s->points[id].instances) return bytes;
    for (i = 0; i < s->header.prototype_count; i++) {
        proto_bytes += (double)s->prototypes[i].size;
        proto_tris += (double)s->prototypes[i].triangles;
    }
    return proto_tris > 0.0 ? bytes + (double)s->points[id].triangles * proto_bytes / proto_tris : bytes;
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
    const uint32_t points = scene->header.point_count;
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

/* ---- layer 7: the loads only occlusion rays asked for (fetch_for) ---- */

/* Nonzero when every ray of the queue is an occlusion ray. */
static int only_occlusion(const scheduler *s, const ray_queue *q)
{
    uint32_t i;
    for (i = 0; i < q->count; i++)
        if (!is_occlusion(&s->slots[q->slots[i]])) return 0;
    return 1;
}

/* Fetches batching point id for its queue (cache_fetch: the paper's LRU
** geometry cache), and, layer 7 (statistics only), books the load, if
** there is one, as the occlusion rays' when they alone asked for it. */
static brt_result fetch_for(scheduler *s, uint32_t id, const ray_queue *q, const geometry **g,
                            brt_error *err)
{
    uint64_t loads = s->stats->batch_loads, bytes = s->stats->disk_bytes_read;
    brt_result r = cache_fetch(&s->cache, id, g, err);
    s->fetch_bytes = s->stats->disk_bytes_read - bytes;
    if (r == BRT_OK && s->stats->batch_loads != loads && only_occlusion(s, q)) {
        s->stats->occlusion_batch_loads += s->stats->batch_loads - loads;
        s->stats->occlusion_disk_bytes_read += s->fetch_bytes;
    }
    return r;
}

/* ---- layer 8: decoded points in core (cache_decode) ---- */

/* Layer 8, decoded points in core: a BVH blob just loaded is decoded to
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

/* ---- layer 9: the next load read ahead (cache_read_ahead) ---- */
/*
** Layer 9, read-ahead: while the threads intersect the rays of one batching
** point (a phase of layer 12), a thread of the cache's own reads the blob
** of the fullest queue left (the likely next load: next_load_guess,
** cache_read_ahead).  The schedule does not change: when the scheduler then
** asks for that blob, cache_load takes the buffer read ahead instead of
** reading (the same bytes, counted then, as a load of the same size would
** be).  When it asks for another blob first, the buffer is kept for later:
** the guess is most often late, not wrong (a point whose queue was fullest
** is served a few batches on), and reading it again would spend the disk
** twice.  It is dropped uncounted when a new guess replaces it.  So every
** count is the one-thread count, and only the wall time differs.  The
** buffer, running or kept, is held beside the budget: one blob more at most
** (README, "Threads").  read_fn is never called by two threads at once: a
** running read-ahead is joined before any other read.  (A point of
** instances' prototypes are not read ahead.)  make bench-threads's row
** "render 25%, --disk-speed 100M" measures it (one thread reads nothing
** ahead).
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

/* Layer 9's guess of the next load: the fullest queue whose batching
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

/* ---- layer 10: a queued ray's walk starts at its proxy entry (clip_to_entry) ---- */

/* Layer 10, the clip: the paper's future work (its section 4.3: "the hit
** points found by intersecting against the proxy geometry could also be
** used to guide the bottom-level acceleration structure traversal").  A
** queued ray's walk in its batching point's BVH starts at entry_t, where
** its proxy cast entered a set voxel first, not at tnear: the nodes and
** triangles it leaves before then are not visited.
**
** WHY IT IS EXACT, UNDER ROUNDING.  The hits of a ray in a point are those
** of the float triangle test with t in [tnear, tlimit]: the BVH finds
** them all at any tnear (bvh.c: t is compared with tnear inclusively, on
** the final float t, and neither the box pads nor the early rejection
** depend on tnear in any other way).  So the clip loses no hit when every
** hit has t >= entry_t, and it has:
**   - the cast returns the least t at which the segment [tnear, tlimit]
**     touches the closed box of a set voxel grown by g, computed as the
**     exact entry of a still larger box and rounded down (svdag.c,
**     "CONSERVATIVE IN FLOAT");
**   - the point o + t_hit d of every hit the float test reports lies in
**     such a grown box: the fact the proxy's conservativeness rests on
**     (the same comment: g covers the float test's hit point and its t
**     clamped into the triangle's padded box, grazing rays included);
** so the segment touches a grown set voxel at t_hit, and entry_t <= t_hit.
** A hit at exactly entry_t is kept, so ties go as before.
** Points of instances: the world point of an instance hit lies within
** the ray's margin of its world triangle (bvh.c, "Instances", steps 1-4),
** and proxy_cast casts only while that margin is at most
** INSTANCE_DILATION of a voxel, the width by which every instanced
** triangle is dilated when voxelized (svdag.c, "Instances"); beyond it
** the ray is admitted untested with entry_t = tnear, and nothing is
** clipped.  The set's instance boxes are grown by the margin as well, so
** each still holds its hits' world points and is left no earlier.
** Exact proxies (layer 5) answer entry_t = tnear, and so does a ray
** received from another process (its entry does not travel); with the
** proxies off no entry is known, and the clip is off.
** The tests: svdag's casts hold entry_t <= t_hit for grazing rays at
** every scale, and for instances sheared and mirrored; clip: the hits
** with the clip on and off, byte for byte.  make bench-order prints the
** node visits per ray it spares -- or adds: boxes a clipped walk starts
** inside all enter at its new tnear and are taken in slot order, not
** nearest first. */
static const brt_ray *clip_to_entry(const scheduler *s, const ray_slot *r, brt_ray *clipped)
{
    if (!s->clip || !(r->entry_t > r->ray.tnear)) return &r->ray;
    *clipped = r->ray;
    clipped->tnear = r->entry_t;
    return clipped;
}

/* ---- layer 11: a batch in the order of its proxy entries (order_batch) ---- */

/* Layer 11, the order: the same future work ("rays could be sorted based
** on their expected hit points", after Moon et al. 2010).  A batch's rays
** are intersected sorted by the Morton code of the voxel where each
** entered the proxy, then by direction octant, so that rays about to
** meet the same nodes and triangles meet them one after another, while
** those are in the processor's caches.  Only the intersections are
** sorted: the walks and the settling keep queue order, so every queue,
** load and finished call is what it was, and no hit depends on the order
** (the tie rule is total).  The sort: a stable LSD radix sort of (key,
** place) pairs, three passes of 11 bits over the 33-bit key, in scratch
** held from the set-up (20 bytes per ray in flight).  make bench-order
** prints the bottom level's Mrays/s with and without it. */
#define ENTRY_VOXEL_BITS 10     /* per axis: a proxy has at most 1024^3 voxels (svdag.c) */
#define ORDER_PLACE_BITS 31     /* a batch's places below the 33-bit key */
#define ORDER_DIGIT 11          /* bits per radix pass: 3 passes */

/* Keeps the proxy entry of a ray the proxy of point key.id admitted: t,
** and the Morton code of the voxel holding o + t d, clamped into the grid
** (the voxel serves the order alone, so its rounding moves no hit). */
static void entry_keep(const scheduler *s, ray_slot *r, float t)
{
    const brt_proxy *proxy = &s->scene->points[r->key.id].proxy;
    uint32_t voxel[3], code = 0;
    int a, bit;
    r->entry_t = t;
    for (a = 0; a < 3; a++) {
        const double q = ((double)r->ray.org[a] + (double)t * r->ray.dir[a] - proxy->origin[a]) / proxy->cell;
        voxel[a] = q > 0 ? (q < proxy->res ? (uint32_t)q : proxy->res - 1) : 0;   /* NaN: 0 */
    }
    for (bit = ENTRY_VOXEL_BITS - 1; bit >= 0; bit--)
        for (a = 2; a >= 0; a--) code = code << 1 | (voxel[a] >> bit & 1u);
    r->entry_voxel = code;
}

/* The sort's scratch, for a batch of every ray in flight (off beyond
** 2^31 of them: a place would not fit its bits). */
static brt_result order_init(scheduler *s)
{
    if (s->capacity > (1u << ORDER_PLACE_BITS)) {
        s->order = 0;
        return BRT_OK;
    }
    s->order_items = malloc((size_t)s->capacity * sizeof *s->order_items);
    s->order_spare = malloc((size_t)s->capacity * sizeof *s->order_spare);
    s->order_slots = malloc((size_t)s->capacity * sizeof *s->order_slots);
    return s->order_items && s->order_spare && s->order_slots ? BRT_OK : BRT_ENOMEM;
}

/* The direction's octant: bit a set when dir[a] is negative (-0 too). */
static uint32_t octant_of(const float dir[3])
{
    return (uint32_t)(signbit(dir[0]) != 0) | (uint32_t)(signbit(dir[1]) != 0) << 1 |
           (uint32_t)(signbit(dir[2]) != 0) << 2;
}

/* The batch slots[0..count) in the order to intersect it: slots itself
** with the order off, else sorted by (entry voxel, octant), stable. */
static const uint32_t *order_batch(scheduler *s, const uint32_t *slots, uint32_t count)
{
    uint64_t *items = s->order_items, *spare = s->order_spare;
    uint32_t i;
    int shift;
    if (!s->order || count < 2) return slots;
    for (i = 0; i < count; i++) {
        const ray_slot *r = &s->slots[slots[i]];
        const uint64_t key = (uint64_t)r->entry_voxel << 3 | octant_of(r->ray.dir);
        items[i] = key << ORDER_PLACE_BITS | i;
    }
    for (shift = ORDER_PLACE_BITS; shift < 64; shift += ORDER_DIGIT) {
        uint32_t start[1u << ORDER_DIGIT], sum = 0, d;
        uint64_t *swap;
        memset(start, 0, sizeof start);
        for (i = 0; i < count; i++) start[items[i] >> shift & ((1u << ORDER_DIGIT) - 1)]++;
        for (d = 0; d < (1u << ORDER_DIGIT); d++) {
            const uint32_t n = start[d];
            start[d] = sum;
            sum += n;
        }
        for (i = 0; i < count; i++) spare[start[items[i] >> shift & ((1u << ORDER_DIGIT) - 1)]++] = items[i];
        swap = items;
        items = spare;
        spare = swap;
    }
    for (i = 0; i < count; i++) s->order_slots[i] = slots[items[i] & ((1u << ORDER_PLACE_BITS) - 1)];
    return s->order_slots;
}

/* ---- layer 12: the scheduler's loop on threads (phases_run) ---- */
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

/* A phase: the rays in slots[0..count), walked; before, for a batch,
** the same rays in layer 11's order (order) intersected with g, the
** batching point whose queue they are. */
typedef struct phase_job {
    scheduler *s;
    const uint32_t *slots, *order;
    const geometry *g;
    brt_result result;          /* of the settling: BRT_ENOMEM from a queue */
} phase_job;

static void intersect_chunk(void *ctx, unsigned thread, size_t first, size_t end)
{
    const phase_job *j = ctx;
    size_t i;
    (void)thread;
    for (i = first; i < end; i++) {
        ray_slot *r = &j->s->slots[j->order[i]];
        brt_ray clipped;
        intersect_slot(j->s, j->g, r, clip_to_entry(j->s, r, &clipped), NULL);   /* layer 10 */
    }
}

static void phase_chunk(void *ctx, unsigned thread, size_t first, size_t end)
{
    const phase_job *j = ctx;
    scheduler *s = j->s;
    walker *w = &s->threads->walkers[thread];
    size_t i;
    for (i = first; i < end; i++) {
        ray_slot *r = &s->slots[j->slots[i]];
        w->uses->stamp = (uint64_t)(i + 1) << 32;   /* ray i's uses come after ray i-1's */
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

/* Layer 12: run_rays in phases (id: the batching point whose queue it is,
** pinned, or NO_ENTRY for new rays; order: the queue in layer 11's
** order): its intersections, then its walks, each split among the
** threads.  Released before the uses are replayed, as the plain loop
** releases it before the walks. */
static brt_result phases_run(scheduler *s, const uint32_t *slots, uint32_t count, uint32_t id,
                             const geometry *g, const uint32_t *order)
{
    phase_job j;
    unsigned i;
    cache_read_ahead(&s->cache, next_load_guess(s));                    /* layer 9 */
    j.s = s;
    j.slots = slots;
    j.order = order;
    j.g = g;
    j.result = BRT_OK;
    if (id != NO_ENTRY) brt_pool_run(&s->threads->pool, intersect_chunk, NULL, &j, count, PHASE_CHUNK);
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
    uint32_t n = s->scene->header.point_count, i;
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

/* ##################################################################### */
/* PART III -- SUPPORT, NOT THE PAPER                                    */
/* ##################################################################### */
/*
** What the method needs to run but the paper does not describe: the
** partition checker (it reads blobs as the cache does) and the direct
** mode's chunks of rays.  The scene file, the direct mode's world, the
** mesh readers, ray and hit files, statistics, utilities and the pool of
** threads have files of their own (scene.c, world.c, mesh.c, base.c).
*/

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
    if (n != s->points[id].triangles)
        return brt_fail(err, BRT_ECHECK, "%s: batching point %u: its BVH holds %u triangles, "
                        "its table entry %u", s->path, id, n, s->points[id].triangles);
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
** the triangles of its distinct prototypes, may exceed point_tris only
** when it uses one prototype. */
static brt_result check_instances(const brt_scene *s, uint32_t id, const instance_set *set,
                                  uint32_t point_tris, unsigned char *seen_inst, brt_error *err)
{
    uint64_t size = 0;
    uint32_t k;
    for (k = 0; k < set->use_count; k++) size += s->prototypes[set->uses[k]].triangles;
    if (size > point_tris && set->use_count > 1)
        return brt_fail(err, BRT_ECHECK, "%s: batching point %u: %llu triangles of %u prototypes, "
                        "more than %u", s->path, id, (unsigned long long)size, set->use_count, point_tris);
    for (k = 0; k < set->count; k++)
        if (!mark_once(seen_inst, set->ids[k]))
            return brt_fail(err, BRT_ECHECK, "%s: instance %u is in two batching points (again in %u)",
                            s->path, set->ids[k], id);
    return BRT_OK;
}

/* Reads point id and marks what it holds. */
static brt_result check_point(const geometry_cache *c, uint32_t id, uint32_t point_tris,
                              unsigned char *seen, unsigned char *seen_inst, brt_error *err)
{
    const brt_scene *s = c->scene;
    uint64_t bytes = 0;
    void *data = NULL;
    blob_view view;
    brt_result r;
    if (!s->points[id].instances && s->points[id].triangles > point_tris)
        return brt_fail(err, BRT_ECHECK, "%s: batching point %u holds %u triangles, more than %u",
                        s->path, id, s->points[id].triangles, point_tris);
    if ((r = blob_read(c, id, &bytes, &data, &view, err)) != BRT_OK) return r;
    r = view.set ? check_instances(s, id, view.set, point_tris, seen_inst, err)
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

brt_result brt_scene_check_partition(const brt_scene *scene, uint32_t point_tris,
                                     brt_error *err)
{
    uint32_t n = scene->header.triangle_count, m = scene->header.instance_count, id, t;
    unsigned char *seen = calloc((size_t)n / 8 + 1, 1), *seen_inst = calloc((size_t)m / 8 + 1, 1);
    geometry_cache c;
    brt_result r = BRT_OK;
    if (!seen || !seen_inst) r = brt_fail(err, BRT_ENOMEM, "%s: out of memory", scene->path);
    memset(&c, 0, sizeof c);
    c.scene = (brt_scene *)scene;   /* blob_read only reads through it */
    c.read_fn = brt_pread_reader;
    for (id = 0; id < scene->header.point_count && r == BRT_OK; id++)
        r = check_point(&c, id, point_tris, seen, seen_inst, err);
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
        brt_intersect_ray(&j->geometry, &j->rays[i], j->tags ? j->tags[i] : 0, &j->hits[i], normal, NULL);
    }
}

void brt_trace_geometry(const geometry *g, const brt_ray *rays, const uint64_t *tags,
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
    brt_trace_geometry(&g, rays, tags, count, hits, normals, threads);
}
