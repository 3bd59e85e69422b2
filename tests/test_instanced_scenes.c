/*
** tests/test_instanced_scenes.c -- the instanced landscape and island
** (examples/lib/scenes.h, "Instanced scenes"): the same bytes from the same
** seed; counts that agree with what the streams deliver; chunks numbered
** 0, c0, c0 + c1, ...; every instance's prototype in range and its
** transform a rotation about y (or a small tilt) times a scale in the
** documented range; instances standing on the world's triangles (a
** vertical ray, brute force, meets the ground at the base point); foliage
** as lone triangles, in the parts the colour table calls leaves; distinct
** colours; bounded prototype boxes; and an instance stream that does not
** hold its instances (resident memory while streaming half a million).
*/
#include "test.h"
#include "util.h"
#include "batchrt.h"
#include "../examples/lib/scenes.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *const kinds[2] = {"landscape", "island"};

static ex_instanced_scene *open_scene(const char *name, double scale, uint64_t seed)
{
    ex_instanced_scene *s;
    brt_error err;
    if (ex_instanced_open(name, scale, seed, &s, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s at scale %g: %s", name, scale, err.message);
        return NULL;
    }
    return s;
}

/* ---- what the streams deliver ---- */

/* A triangle or instance stream's log: the bytes (when keep), a hash of
** them and of the chunk sizes, and whether every chunk's first was the
** count so far. */
typedef struct stream_log {
    int keep;
    unsigned char *bytes;
    size_t size, cap;
    uint64_t count, hash;
    uint32_t chunks, largest_chunk;
    int misnumbered;
} stream_log;

static brt_result log_chunk(stream_log *log, const void *items, size_t item_bytes,
                            uint32_t count, uint32_t first)
{
    const unsigned char *p = items;
    size_t n = item_bytes * count, i;
    if (first != log->count) log->misnumbered = 1;
    for (i = 0; i < n; i++) log->hash = (log->hash ^ p[i]) * 1099511628211ull;
    log->hash = (log->hash ^ count) * 1099511628211ull;
    if (log->keep) {
        if (log->size + n > log->cap) {
            size_t cap = 2 * (log->size + n);
            unsigned char *bigger = realloc(log->bytes, cap);
            if (!bigger) return BRT_ENOMEM;
            log->bytes = bigger;
            log->cap = cap;
        }
        memcpy(log->bytes + log->size, items, n);
        log->size += n;
    }
    log->count += count;
    log->chunks++;
    if (count > log->largest_chunk) log->largest_chunk = count;
    return BRT_OK;
}

static brt_result log_triangles(void *user, const float *corners, uint32_t count, uint32_t first,
                                brt_error *err)
{
    (void)err;
    return log_chunk(user, corners, 36, count, first);
}

static brt_result log_instances(void *user, const brt_instance *instances, uint32_t count,
                                uint32_t first, brt_error *err)
{
    (void)err;
    return log_chunk(user, instances, sizeof *instances, count, first);
}

static void log_init(stream_log *log, int keep)
{
    memset(log, 0, sizeof *log);
    log->keep = keep;
    log->hash = 14695981039346656037ull;
}

/* The world, one prototype (id >= 0) or the instances (id -1) into log. */
static int run_stream(const brt_scene_source *src, int id, stream_log *log)
{
    brt_error err;
    brt_result r;
    if (id == -2) r = src->world.run(src->world.user, log_triangles, log, &err);
    else if (id >= 0) r = src->prototype(src->user, (uint32_t)id, log_triangles, log, &err);
    else r = src->instances(src->user, log_instances, log, &err);
    if (r != BRT_OK) test_fail_at(__FILE__, __LINE__, "stream %d: %s", id, err.message);
    return r == BRT_OK;
}

#define WORLD (-2)
#define INSTANCES (-1)

/* The hash of every stream of a scene, in order (world, prototypes,
** instances), and whether all chunks were numbered right. */
static uint64_t scene_hash(const char *name, double scale, uint64_t seed, int *misnumbered)
{
    ex_instanced_scene *s = open_scene(name, scale, seed);
    brt_scene_source src;
    uint64_t h = 0;
    int id;
    if (!s) return 0;
    ex_instanced_source(s, &src);
    for (id = WORLD; id < (int)src.prototype_count; id++) {
        stream_log log;
        log_init(&log, 0);
        if (!run_stream(&src, id, &log)) break;
        h = brt_mix64(h ^ log.hash);
        *misnumbered |= log.misnumbered;
    }
    ex_instanced_close(s);
    return h;
}

static void test_same_seed_same_bytes(void)
{
    uint64_t seed = test_seed();
    int k, bad = 0;
    for (k = 0; k < 2; k++) {
        uint64_t a = scene_hash(kinds[k], 0.3, seed, &bad), b = scene_hash(kinds[k], 0.3, seed, &bad);
        uint64_t c = scene_hash(kinds[k], 0.3, seed + 1, &bad);
        EXPECT(a == b, "%s: seed %llu gave different streams twice", kinds[k],
               (unsigned long long)seed);
        EXPECT(a != c, "%s: seeds %llu and %llu gave the same streams", kinds[k],
               (unsigned long long)seed, (unsigned long long)seed + 1);
        EXPECT(!bad, "%s: a chunk's first was not the count of the chunks before", kinds[k]);
    }
}

/* ---- counts ---- */

/* The counts of the open scene and of ex_instanced_counts (which do not
** depend on the seed) against the streams: world + each prototype once,
** world + each instance's prototype. */
static void check_counts_against_streams(const char *name, double scale)
{
    ex_instanced_scene *s = open_scene(name, scale, test_seed());
    brt_scene_source src;
    stream_log log;
    uint64_t proto_tris[16], unique, instanced, sum_unique, sum_instanced;
    uint32_t instances, i;
    int id;
    if (!s) return;
    ex_instanced_source(s, &src);
    CHECK(src.prototype_count > 0 && src.prototype_count <= 16, "%u prototypes", src.prototype_count);
    log_init(&log, 0);
    run_stream(&src, WORLD, &log);
    sum_unique = sum_instanced = log.count;
    EXPECT(log.count == ex_instanced_world_triangles(s), "%s: world %llu, stream %llu", name,
           (unsigned long long)ex_instanced_world_triangles(s), (unsigned long long)log.count);
    for (id = 0; id < (int)src.prototype_count; id++) {
        log_init(&log, 0);
        run_stream(&src, id, &log);
        proto_tris[id] = log.count;
        sum_unique += log.count;
        EXPECT(log.count > 0 && log.count == ex_instanced_prototype_triangles(s, (uint32_t)id),
               "%s: prototype %d streams %llu triangles", name, id, (unsigned long long)log.count);
    }
    log_init(&log, 1);
    run_stream(&src, INSTANCES, &log);
    for (i = 0; i < log.count; i++) {
        const brt_instance *inst = (const brt_instance *)log.bytes + i;
        if (inst->prototype < src.prototype_count) sum_instanced += proto_tris[inst->prototype];
    }
    ex_instanced_counts(name, scale, &unique, &instanced, &instances);
    EXPECT(unique == sum_unique && ex_instanced_unique(s) == sum_unique, "%s at %g: unique %llu, "
           "the streams %llu", name, scale, (unsigned long long)unique, (unsigned long long)sum_unique);
    EXPECT(instanced == sum_instanced && ex_instanced_instanced(s) == sum_instanced,
           "%s at %g: instanced %llu, the streams %llu", name, scale, (unsigned long long)instanced,
           (unsigned long long)sum_instanced);
    EXPECT(instances == log.count && ex_instanced_instance_count(s) == log.count,
           "%s at %g: %u instances, %llu streamed", name, scale, instances,
           (unsigned long long)log.count);
    free(log.bytes);
    ex_instanced_close(s);
}

/* The sizes scenes.h promises: about 100 thousand unique triangles and at
** most tens of millions instanced at scale 1; the landscape at scale 285
** about the paper's 26 M unique and over 4 G instanced; the island at 1750
** about its 143 M unique and over 20 G instanced. */
static void test_counts_agree_with_streams(void)
{
    uint64_t unique, instanced;
    uint32_t instances;
    int k;
    for (k = 0; k < 2; k++) {
        check_counts_against_streams(kinds[k], 0.05);
        check_counts_against_streams(kinds[k], 1);
        ex_instanced_counts(kinds[k], 1, &unique, &instanced, &instances);
        EXPECT(unique >= 60000 && unique <= 150000 && instanced <= 50000000 && instanced > 10 * unique,
               "%s at scale 1: %llu unique, %llu instanced", kinds[k], (unsigned long long)unique,
               (unsigned long long)instanced);
    }
    ex_instanced_counts("landscape", 285, &unique, &instanced, &instances);
    EXPECT(unique >= 23000000 && unique <= 29000000 && instanced >= 4000000000ull,
           "landscape at 285: %llu unique, %llu instanced", (unsigned long long)unique,
           (unsigned long long)instanced);
    ex_instanced_counts("island", 1750, &unique, &instanced, &instances);
    EXPECT(unique >= 125000000 && unique <= 160000000 && instanced >= 20000000000ull,
           "island at 1750: %llu unique, %llu instanced", (unsigned long long)unique,
           (unsigned long long)instanced);
    ex_instanced_counts("teapot", 1, &unique, &instanced, &instances);
    EXPECT(unique == 0 && instanced == 0 && instances == 0, "counts of an unknown scene");
}

/* Scale 2: the landscape's terrain takes several triangle batches and its
** instances several chunks. */
static void test_chunks_numbered(void)
{
    ex_instanced_scene *s = open_scene("landscape", 2, test_seed());
    brt_scene_source src;
    int id;
    if (!s) return;
    ex_instanced_source(s, &src);
    for (id = WORLD; id < (int)src.prototype_count; id++) {
        stream_log log;
        log_init(&log, 0);
        run_stream(&src, id, &log);
        EXPECT(!log.misnumbered && log.count > 0, "stream %d: chunks misnumbered", id);
        if (id == WORLD) EXPECT(log.chunks >= 3, "the world came in %u chunks", log.chunks);
        if (id == INSTANCES)
            EXPECT(log.chunks >= 3 && log.largest_chunk <= EX_INSTANCE_CHUNK,
                   "%u instance chunks, the largest %u", log.chunks, log.largest_chunk);
    }
    ex_instanced_close(s);
}

/* ---- instances ---- */

static double dot3(const double a[3], const double b[3])
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

/* M's columns: orthogonal, of one length in the scale range, M's y column
** within the tilt of up, condition numbers (2-norm 1, infinity norm at
** most 3 for a rotation) far below BRT_MAX_CONDITION.  Returns the tilt. */
static double check_transform(const char *name, uint32_t i, const brt_instance *inst)
{
    double col[3][3], len[3], tilt, row_max = 0, inv_max = 0;
    int r, c, k;
    for (k = 0; k < 12; k++)
        if (!isfinite(inst->xform[k])) {
            test_fail_at(__FILE__, __LINE__, "%s: instance %u: xform[%d] not finite", name, i, k);
            return 0;
        }
    for (c = 0; c < 3; c++) {
        for (r = 0; r < 3; r++) col[c][r] = inst->xform[4 * r + c];
        len[c] = sqrt(dot3(col[c], col[c]));
    }
    for (c = 0; c < 3; c++) {
        EXPECT(fabs(len[c] - len[0]) <= 1e-5 * len[0] && len[c] >= EX_INSTANCE_SCALE_MIN * (1 - 1e-6)
               && len[c] <= EX_INSTANCE_SCALE_MAX * (1 + 1e-6),
               "%s: instance %u: column %d has length %g (column 0: %g)", name, i, c, len[c], len[0]);
        EXPECT(fabs(dot3(col[c], col[(c + 1) % 3])) <= 1e-5 * len[0] * len[0],
               "%s: instance %u: columns %d and %d not orthogonal", name, i, c, (c + 1) % 3);
    }
    for (r = 0; r < 3; r++) {   /* M^-1 = M^T / len^2 */
        double row = 0, inv = 0;
        for (c = 0; c < 3; c++) {
            row += fabs(inst->xform[4 * r + c]);
            inv += fabs(inst->xform[4 * c + r]) / (len[0] * len[0]);
        }
        row_max = fmax(row_max, row);
        inv_max = fmax(inv_max, inv);
    }
    EXPECT(row_max * inv_max <= 3.001 && row_max * inv_max < BRT_MAX_CONDITION,
           "%s: instance %u: condition number %g", name, i, row_max * inv_max);
    tilt = acos(fmin(1, col[1][1] / len[1]));
    EXPECT(tilt <= EX_INSTANCE_MAX_TILT + 1e-4, "%s: instance %u tilted %g rad", name, i, tilt);
    return tilt;
}

static void test_instances_well_formed(void)
{
    int k;
    for (k = 0; k < 2; k++) {
        ex_instanced_scene *s = open_scene(kinds[k], 1, test_seed());
        brt_scene_source src;
        stream_log log;
        uint32_t i, tilted = 0, runs = 0;
        int last = -1;
        if (!s) return;
        ex_instanced_source(s, &src);
        log_init(&log, 1);
        run_stream(&src, INSTANCES, &log);
        for (i = 0; i < log.count && !test_failed(); i++) {
            const brt_instance *inst = (const brt_instance *)log.bytes + i;
            brt_instance again;
            CHECK(inst->prototype < src.prototype_count, "%s: instance %u of prototype %u", kinds[k],
                  i, inst->prototype);
            EXPECT((int)inst->prototype == ex_instanced_instance_prototype(s, i),
                   "%s: instance %u: prototype %u, lookup %d", kinds[k], i, inst->prototype,
                   ex_instanced_instance_prototype(s, i));
            runs += (int)inst->prototype != last;
            last = (int)inst->prototype;
            ex_instanced_instance(s, i, &again);
            EXPECT(memcmp(&again, inst, sizeof again) == 0, "%s: instance %u made alone differs",
                   kinds[k], i);
            tilted += check_transform(kinds[k], i, inst) > 1e-6;
        }
        EXPECT(runs == src.prototype_count, "%s: %u runs of prototypes, %u prototypes", kinds[k],
               runs, src.prototype_count);
        EXPECT(tilted > 0.05 * log.count && tilted < 0.15 * log.count, "%s: %u of %llu tilted",
               kinds[k], tilted, (unsigned long long)log.count);
        EXPECT(ex_instanced_instance_prototype(s, (uint32_t)log.count) == -1,
               "%s: a prototype for instance %llu of %llu", kinds[k],
               (unsigned long long)log.count, (unsigned long long)log.count);
        free(log.bytes);
        ex_instanced_close(s);
    }
}

/* The first world triangle a vertical ray from 10 m above (x, z) meets,
** by brute force: its height, or NAN. */
static double ground_under(const stream_log *world, double x, double y, double z)
{
    const float *c = (const float *)world->bytes;
    brt_ray ray;
    brt_hit best;
    uint64_t t;
    float tt, u, v;
    ray.org[0] = (float)x;
    ray.org[1] = (float)(y + 10);
    ray.org[2] = (float)z;
    ray.dir[0] = ray.dir[2] = 0;
    ray.dir[1] = -1;
    ray.tnear = 0;
    ray.tfar = INFINITY;
    best.t = INFINITY;
    for (t = 0; t < world->count; t++)
        if (brt_intersect_triangle(&ray, c + 9 * t, c + 9 * t + 3, c + 9 * t + 6, &tt, &u, &v)
            && tt < best.t)
            best.t = tt;
    return isfinite(best.t) ? (double)ray.org[1] - best.t : NAN;
}

/* Every 7th instance: its base point (the translation) is where a vertical
** ray meets the world's triangles, to a millimetre; on the island, on land
** above the sea. */
static void test_instances_stand_on_the_world(void)
{
    int k;
    for (k = 0; k < 2; k++) {
        ex_instanced_scene *s = open_scene(kinds[k], 0.3, test_seed());
        brt_scene_source src;
        stream_log world, inst;
        uint64_t i, checked = 0;
        if (!s) return;
        ex_instanced_source(s, &src);
        log_init(&world, 1);
        log_init(&inst, 1);
        run_stream(&src, WORLD, &world);
        run_stream(&src, INSTANCES, &inst);
        for (i = 0; i < inst.count && !test_failed(); i += 7, checked++) {
            const brt_instance *p = (const brt_instance *)inst.bytes + i;
            double x = p->xform[3], y = p->xform[7], z = p->xform[11];
            double ground = ground_under(&world, x, y, z);
            EXPECT(fabs(ground - y) <= 1e-3, "%s: instance %llu at %g %g %g, the ground at %g",
                   kinds[k], (unsigned long long)i, x, y, z, ground);
            if (k == 1) EXPECT(y > 0, "%s: instance %llu at height %g: in the sea", kinds[k],
                               (unsigned long long)i, y);
        }
        if (!test_failed())
            EXPECT(checked > 100, "%s: only %llu instances checked", kinds[k],
                   (unsigned long long)checked);
        free(world.bytes);
        free(inst.bytes);
        ex_instanced_close(s);
    }
}

/* ---- prototypes and colours ---- */

static int compare_positions(const void *a, const void *b)
{
    return memcmp(a, b, 12);
}

/* How many triangles of a stream have three corner positions that no
** other corner of the stream shares (a lone triangle: a leaf, a needle);
** *first_lone: the lowest prim of one. */
static uint64_t lone_triangles(const stream_log *log, uint64_t *first_lone)
{
    size_t n = 3 * (size_t)log->count;
    float *sorted = malloc(12 * n);
    uint64_t t, lone = 0;
    if (!sorted) return 0;
    memcpy(sorted, log->bytes, 12 * n);
    qsort(sorted, n, 12, compare_positions);
    *first_lone = UINT64_MAX;
    for (t = 0; t < log->count; t++) {
        int c, shared = 0;
        for (c = 0; c < 3; c++) {
            const float *p = (const float *)log->bytes + 9 * t + 3 * c;
            const float *hit = bsearch(p, sorted, n, 12, compare_positions);
            size_t at = (size_t)(hit - sorted) / 3;
            /* bsearch finds one of the equal keys: shared when a neighbour is equal too */
            shared |= (at > 0 && memcmp(sorted + 3 * (at - 1), p, 12) == 0)
                    || (at + 1 < n && memcmp(sorted + 3 * (at + 1), p, 12) == 0);
        }
        if (!shared) {
            if (lone == 0) *first_lone = t;
            lone++;
        }
    }
    free(sorted);
    return lone;
}

static int prototype_named(const ex_instanced_scene *s, const char *name)
{
    uint32_t k;
    for (k = 0; k < ex_instanced_prototype_count(s); k++)
        if (strcmp(ex_instanced_prototype_name(s, k), name) == 0) return (int)k;
    return -1;
}

/* The first instance of a prototype. */
static uint32_t instance_of(const ex_instanced_scene *s, int proto)
{
    uint32_t i;
    for (i = 0; i < ex_instanced_instance_count(s); i++)
        if (ex_instanced_instance_prototype(s, i) == proto) return i;
    return BRT_NO_INST;
}

/* Foliage prototypes: at least a share of the foliage part of the colour
** table lone triangles (a palm's fronds also hold their rachises), none in
** the bark part: the bark (grids) shares its vertices. */
static void check_foliage(const ex_instanced_scene *s, const char *proto_name, ex_material foliage,
                          uint64_t at_least, double share)
{
    brt_scene_source src;
    stream_log log;
    int proto = prototype_named(s, proto_name);
    uint32_t inst = instance_of(s, proto);
    uint64_t lone, first_lone = 0, t, foliage_tris = 0;
    CHECK(proto >= 0 && inst != BRT_NO_INST, "no %s instance", proto_name);
    ex_instanced_source(s, &src);
    log_init(&log, 1);
    run_stream(&src, proto, &log);
    lone = lone_triangles(&log, &first_lone);
    for (t = 0; t < log.count; t++)
        foliage_tris += ex_instanced_material(s, inst, (uint32_t)t) == foliage;
    EXPECT(lone >= at_least && lone >= share * (double)foliage_tris && lone <= foliage_tris,
           "%s: %llu lone triangles of %llu, %llu in its foliage part", proto_name,
           (unsigned long long)lone, (unsigned long long)log.count, (unsigned long long)foliage_tris);
    EXPECT(ex_instanced_material(s, inst, 0) == EX_MAT_BARK && first_lone > 0
           && ex_instanced_material(s, inst, (uint32_t)first_lone) == foliage,
           "%s: prim 0 is material %d, the first lone triangle %llu is %d", proto_name,
           (int)ex_instanced_material(s, inst, 0), (unsigned long long)first_lone,
           (int)ex_instanced_material(s, inst, (uint32_t)first_lone));
    free(log.bytes);
}

static void test_foliage_is_lone_triangles(void)
{
    ex_instanced_scene *land = open_scene("landscape", 1, test_seed());
    ex_instanced_scene *isle = open_scene("island", 1, test_seed());
    if (land && isle) {
        check_foliage(land, "oak", EX_MAT_LEAVES, 2000, 0.99);
        check_foliage(land, "birch", EX_MAT_LEAVES, 1000, 0.99);
        check_foliage(land, "spruce", EX_MAT_NEEDLES, 1000, 0.99);
        check_foliage(isle, "palm", EX_MAT_FRONDS, 400, 0.8);
    }
    ex_instanced_close(land);
    ex_instanced_close(isle);
}

/* Each prototype's box: a few tens of metres at most, about its base
** point, and reaching into the ground; nothing spans the scene. */
static void test_prototype_boxes_bounded(void)
{
    int k;
    for (k = 0; k < 2; k++) {
        ex_instanced_scene *s = open_scene(kinds[k], 4, test_seed());
        brt_scene_source src;
        uint32_t id;
        if (!s) return;
        ex_instanced_source(s, &src);
        for (id = 0; id < src.prototype_count; id++) {
            stream_log log;
            const float *c;
            float lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
            uint64_t i;
            int a;
            log_init(&log, 1);
            run_stream(&src, (int)id, &log);
            c = (const float *)log.bytes;
            for (i = 0; i < 3 * log.count; i++)
                for (a = 0; a < 3; a++) {
                    lo[a] = fminf(lo[a], c[3 * i + a]);
                    hi[a] = fmaxf(hi[a], c[3 * i + a]);
                }
            EXPECT(hi[1] > 0 && hi[1] <= 25 && lo[1] >= -2 && lo[1] <= -0.05 && lo[0] >= -12 && hi[0] <= 12
                   && lo[2] >= -12 && hi[2] <= 12, "%s: %s spans %g %g %g .. %g %g %g", kinds[k],
                   ex_instanced_prototype_name(s, id), lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]);
            free(log.bytes);
        }
        ex_instanced_close(s);
    }
}

static void test_colours(void)
{
    static const ex_material distinct[] = {EX_MAT_TERRAIN, EX_MAT_ROCK, EX_MAT_SAND, EX_MAT_SEA,
                                           EX_MAT_BARK, EX_MAT_LEAVES, EX_MAT_NEEDLES,
                                           EX_MAT_FRONDS, EX_MAT_GRASS, EX_MAT_NONE};
    ex_instanced_scene *land = open_scene("landscape", 0.3, 1);
    ex_instanced_scene *isle = open_scene("island", 0.3, 1);
    size_t a, b;
    float ca[3], cb[3];
    for (a = 0; a < sizeof distinct / sizeof *distinct; a++)
        for (b = a + 1; b < sizeof distinct / sizeof *distinct; b++) {
            ex_material_colour(distinct[a], ca);
            ex_material_colour(distinct[b], cb);
            EXPECT(memcmp(ca, cb, sizeof ca) != 0, "materials %d and %d share a colour",
                   (int)distinct[a], (int)distinct[b]);
        }
    if (land && isle) {
        uint32_t world = (uint32_t)ex_instanced_world_triangles(land);
        uint32_t rock = instance_of(land, prototype_named(land, "boulder"));
        uint32_t tuft = instance_of(land, prototype_named(land, "grass"));
        EXPECT(ex_instanced_material(land, BRT_NO_INST, 0) == EX_MAT_TERRAIN
               && ex_instanced_material(land, BRT_NO_INST, world - 1) == EX_MAT_ROCK
               && ex_instanced_material(land, BRT_NO_INST, world) == EX_MAT_NONE,
               "landscape world: %d, %d, %d", (int)ex_instanced_material(land, BRT_NO_INST, 0),
               (int)ex_instanced_material(land, BRT_NO_INST, world - 1),
               (int)ex_instanced_material(land, BRT_NO_INST, world));
        EXPECT(ex_instanced_material(land, rock, 0) == EX_MAT_ROCK
               && ex_instanced_material(land, tuft, 0) == EX_MAT_GRASS
               && ex_instanced_material(land, ex_instanced_instance_count(land), 0) == EX_MAT_NONE,
               "rock %d, grass %d", (int)ex_instanced_material(land, rock, 0),
               (int)ex_instanced_material(land, tuft, 0));
        EXPECT(ex_instanced_material(isle, BRT_NO_INST, 0) == EX_MAT_SEA
               && ex_instanced_material(isle, BRT_NO_INST, 1) == EX_MAT_SEA
               && ex_instanced_material(isle, BRT_NO_INST, 2) == EX_MAT_SAND,
               "island world: %d %d %d", (int)ex_instanced_material(isle, BRT_NO_INST, 0),
               (int)ex_instanced_material(isle, BRT_NO_INST, 1),
               (int)ex_instanced_material(isle, BRT_NO_INST, 2));
        ex_instanced_colour(isle, BRT_NO_INST, 0, ca);
        ex_material_colour(EX_MAT_SEA, cb);
        EXPECT(memcmp(ca, cb, sizeof ca) == 0, "the sea's colour is not its material's");
    }
    ex_instanced_close(land);
    ex_instanced_close(isle);
}

static void test_errors(void)
{
    ex_instanced_scene *s = (ex_instanced_scene *)&s;
    brt_scene_source src;
    brt_error err;
    stream_log log;
    EXPECT(ex_instanced_open("crown", 1, 1, &s, &err) == BRT_EARG && s == NULL
           && strstr(err.message, "crown"), "crown opened: %s", err.message);
    EXPECT(ex_instanced_open("landscape", 0, 1, &s, &err) == BRT_EARG, "scale 0 accepted");
    EXPECT(ex_instanced_open("island", nan(""), 1, &s, &err) == BRT_EARG, "NaN scale accepted");
    EXPECT(ex_instanced_open("island", 2 * EX_SCENE_MAX_SCALE, 1, &s, &err) == BRT_EARG,
           "scale %g accepted", 2 * EX_SCENE_MAX_SCALE);
    s = open_scene("island", 0.05, 1);
    if (!s) return;
    ex_instanced_source(s, &src);
    log_init(&log, 0);
    EXPECT(src.prototype(src.user, src.prototype_count, log_triangles, &log, &err) == BRT_EARG
           && log.count == 0, "prototype %u streamed", src.prototype_count);
    EXPECT(ex_instanced_prototype_name(s, src.prototype_count) == NULL
           && ex_instanced_prototype_triangles(s, src.prototype_count) == 0, "a prototype too many");
    ex_instanced_close(s);
}

/* ---- memory ---- */

/* Resident bytes now (Linux /proc/self/statm), 0 when unknown. */
static double resident_bytes(void)
{
    FILE *f = fopen("/proc/self/statm", "r");
    unsigned long size = 0, resident = 0;
    if (!f) return 0;
    if (fscanf(f, "%lu %lu", &size, &resident) != 2) resident = 0;
    fclose(f);
    return (double)resident * 4096.0;
}

typedef struct rss_watch {
    double peak;
    uint64_t count;
} rss_watch;

static brt_result watch_instances(void *user, const brt_instance *instances, uint32_t count,
                                  uint32_t first, brt_error *err)
{
    rss_watch *w = user;
    double now = resident_bytes();
    (void)instances;
    (void)first;
    (void)err;
    w->count += count;
    if (now > w->peak) w->peak = now;
    return BRT_OK;
}

/* Scale 100: 575 thousand instances, 30 MB held as brt_instances.  The
** resident memory from before opening the scene to the end of its
** instance stream grows by less than a sixth of that. */
static void test_instances_not_held(void)
{
    ex_instanced_scene *s;
    brt_scene_source src;
    brt_error err;
    rss_watch w = {0, 0};
    double before, held;
    if (!tu_rss_is_meaningful()) return;
    before = resident_bytes();
    if (before == 0) {
        test_skip("no /proc/self/statm");
        return;
    }
    s = open_scene("landscape", 100, 1);
    if (!s) return;
    ex_instanced_source(s, &src);
    held = (double)ex_instanced_instance_count(s) * sizeof(brt_instance);
    EXPECT(src.instances(src.user, watch_instances, &w, &err) == BRT_OK, "%s", err.message);
    EXPECT(w.count == ex_instanced_instance_count(s) && held > 25e6, "%llu instances streamed",
           (unsigned long long)w.count);
    EXPECT(w.peak - before < held / 6, "resident memory grew by %.1f MB while streaming %.1f MB "
           "of instances", (w.peak - before) / 1e6, held / 1e6);
    ex_instanced_close(s);
}

void suite_instanced_scenes(void)
{
    test_run("scenes: instanced, same seed same bytes", test_same_seed_same_bytes);
    test_run("scenes: instanced, counts agree with the streams", test_counts_agree_with_streams);
    test_run("scenes: instanced, chunks numbered", test_chunks_numbered);
    test_run("scenes: instanced, instances well formed", test_instances_well_formed);
    test_run("scenes: instanced, instances stand on the world", test_instances_stand_on_the_world);
    test_run("scenes: instanced, foliage is lone triangles", test_foliage_is_lone_triangles);
    test_run("scenes: instanced, prototype boxes bounded", test_prototype_boxes_bounded);
    test_run("scenes: instanced, colours", test_colours);
    test_run("scenes: instanced, errors", test_errors);
    test_run("scenes: instanced, instances not held", test_instances_not_held);
}
