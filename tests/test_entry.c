/*
** tests/test_entry.c -- layers 10 and 11 of batchrt.c: where a queued ray
** entered its proxy guides the bottom level (the paper's section 4.3).
** The clip (a ray's walk in a batching point starts at its proxy entry)
** and the order (a batch intersected sorted by entry voxel, then
** direction octant) change no byte: every hit and occlusion answer
** against the direct mode or brute force, with each use on and off, in
** and out of core, with one thread and two, on plain and instanced scenes
** and on walls lying in voxel planes.  The order is held to a model
** written apart (a stable sort of the queue order by its own Morton key)
** and the walks to their order without it (the finished calls); the clip
** to its point (it moves tnear, and visits no more BVH nodes).
*/
#include "test.h"
#include "util.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* ---- fixtures: a scene file, rays and their reference answers ---------- */

typedef struct fixture {
    const char *name;
    brt_scene *scene;
    brt_ray *rays;
    brt_hit *want;              /* direct mode / brute force */
    uint8_t *occluded;          /* brute force */
    size_t count;
} fixture;

static void fixture_free(fixture *f)
{
    if (f->scene) brt_scene_close(f->scene);
    free(f->rays);
    free(f->want);
    free(f->occluded);
    memset(f, 0, sizeof *f);
}

/* Rays of every kind of tu_make_ray around s, per_kind each, plus rays
** grazing the planes z = k (k an integer in the box): in a plane, along x
** or y.  Returns their count. */
static size_t make_rays(const tu_scene *s, size_t per_kind, uint64_t seed, brt_ray **out)
{
    float lo[3], hi[3];
    uint64_t st = seed;
    size_t n = per_kind * (TU_RAY_KINDS + 1), i = 0, k;
    brt_ray *rays = malloc(n * sizeof *rays);
    int kind;
    tu_scene_bounds(s, lo, hi);
    for (kind = 0; kind < TU_RAY_KINDS; kind++)
        for (k = 0; k < per_kind; k++) tu_make_ray(s, lo, hi, kind, &st, &rays[i++]);
    for (k = 0; k < per_kind; k++) {
        brt_ray *r = &rays[i++];
        const int along = (int)(k & 1);
        r->org[0] = tu_rnd(&st, lo[0], hi[0]);
        r->org[1] = tu_rnd(&st, lo[1], hi[1]);
        r->org[2] = floorf(tu_rnd(&st, lo[2], hi[2]));
        r->org[along] = lo[along] - 1.0f;
        r->dir[0] = r->dir[1] = r->dir[2] = 0.0f;
        r->dir[along] = 1.0f;
        r->dir[1 - along] = (k & 2) ? 0.0f : tu_rnd(&st, -0.2f, 0.2f);
        r->tnear = 0.0f;
        r->tfar = INFINITY;
    }
    *out = rays;
    return n;
}

/* A plain scene's fixture: its scene file (point_tris, res) and the
** reference answers of make_rays's rays. */
static int plain_fixture(fixture *f, const char *name, const tu_scene *s, uint32_t point_tris,
                         uint32_t res, size_t per_kind)
{
    brt_bvh *bvh = NULL;
    size_t i;
    memset(f, 0, sizeof *f);
    f->name = name;
    f->count = make_rays(s, per_kind, test_seed() + 7, &f->rays);
    f->want = malloc(f->count * sizeof *f->want);
    f->occluded = malloc(f->count);
    if (!f->want || !f->occluded || brt_bvh_build(s->pos, s->idx, s->tcount, NULL, &bvh) != BRT_OK) return 0;
    for (i = 0; i < f->count; i++) {
        brt_hit_clear(&f->want[i]);
        brt_bvh_intersect(bvh, &f->rays[i], &f->want[i]);
        f->occluded[i] = (uint8_t)tu_brute_occluded(s, &f->rays[i]);
    }
    brt_bvh_free(bvh);
    f->scene = tu_build_scene(s, point_tris, res, 1, tu_scratch(name));
    return f->scene != NULL;
}

/* Random thin triangles about the origin (a prototype). */
static void prototype_soup(tu_scene *s, uint64_t *st, uint32_t n)
{
    uint32_t i;
    for (i = 0; i < n; i++) {
        const float cx = tu_rnd(st, -1, 1), cy = tu_rnd(st, -1, 1), cz = tu_rnd(st, -1, 1);
        const uint32_t a = tu_add_vertex(s, cx, cy, cz);
        const uint32_t b = tu_add_vertex(s, cx + tu_rnd(st, -0.6f, 0.6f), cy + tu_rnd(st, -0.6f, 0.6f), cz);
        const uint32_t c = tu_add_vertex(s, cx + tu_rnd(st, -0.05f, 0.05f), cy, cz + tu_rnd(st, -0.6f, 0.6f));
        tu_add_triangle(s, a, b, c);
    }
}

/* Instances rotated, sheared, scaled and mirrored, on a lattice of
** translations: the margins of instance boxes and the dilation of their
** proxies at work.  The reference is brute force over every instance. */
static int instanced_fixture(fixture *f, size_t per_kind)
{
    tu_instanced inst;
    brt_scene_source source;
    brt_scene_options opt;
    brt_error err;
    tu_scene hull = {0};                 /* instance corners, for the rays' box */
    uint64_t st = test_seed() + 11;
    uint32_t p, i;
    size_t r;
    memset(f, 0, sizeof *f);
    memset(&inst, 0, sizeof inst);
    f->name = "entry-inst.brs";
    inst.proto_count = 3;
    for (p = 0; p < inst.proto_count; p++) prototype_soup(&inst.protos[p], &st, 40);
    for (i = 0; i < 150; i++) {
        float m[12];
        const float angle = tu_rnd(&st, 0, 6.2831853f), c = cosf(angle), sn = sinf(angle);
        const float sx = tu_rnd(&st, 0.5f, 2.0f) * (i % 3 == 0 ? -1.0f : 1.0f), sh = tu_rnd(&st, -0.7f, 0.7f);
        m[0] = c * sx; m[1] = -sn + sh; m[2] = 0; m[3] = 4.0f * (float)(i % 6);
        m[4] = sn * sx; m[5] = c; m[6] = 0.3f * sh; m[7] = 4.0f * (float)(i / 6 % 5);
        m[8] = 0; m[9] = sh; m[10] = i % 4 == 0 ? -1.5f : 1.0f; m[11] = 3.0f * (float)(i / 30);
        tu_add_instance(&inst, i % inst.proto_count, m);
        tu_add_vertex(&hull, m[3] - 3, m[7] - 3, m[11] - 3);
        tu_add_vertex(&hull, m[3] + 3, m[7] + 3, m[11] + 3);
    }
    for (i = 0; i + 2 < hull.vcount; i += 3) tu_add_triangle(&hull, i, i + 1, i + 2);
    f->count = make_rays(&hull, per_kind, test_seed() + 13, &f->rays);
    f->want = malloc(f->count * sizeof *f->want);
    f->occluded = malloc(f->count);
    for (r = 0; f->want && f->occluded && r < f->count; r++) {
        brt_hit_clear(&f->want[r]);
        tu_instanced_brute(&inst, &f->rays[r], &f->want[r]);
        f->occluded[r] = (uint8_t)tu_instanced_brute_occluded(&inst, &f->rays[r]);
    }
    tu_instanced_source(&inst, &source);
    memset(&opt, 0, sizeof opt);
    opt.point_tris = 60;
    opt.proxy_res = 32;
    opt.threads = 1;
    if (f->want && f->occluded &&
        brt_scene_build_source(&source, &opt, 1, tu_scratch(f->name), &err) == BRT_OK &&
        brt_scene_open(tu_scratch(f->name), &f->scene, &err) != BRT_OK)
        f->scene = NULL;
    tu_instanced_free(&inst);
    tu_scene_free(&hull);
    return f->scene != NULL;
}

/* Walls in the planes x, y, z = 0..4 (unit squares, two triangles each):
** each batching point's proxy grid is fitted to its box, whose faces lie
** on walls, so rays meet walls exactly where they enter set voxels. */
static void walls(tu_scene *s)
{
    int axis, k, u, v;
    for (axis = 0; axis < 3; axis++)
        for (k = 0; k <= 4; k++)
            for (u = 0; u < 4; u++)
                for (v = 0; v < 4; v++) {
                    uint32_t q[4];
                    int c;
                    if ((u + v + k) % 3 == 0) continue;       /* holes to see through */
                    for (c = 0; c < 4; c++) {
                        float p[3];
                        p[axis] = (float)k;
                        p[(axis + 1) % 3] = (float)(u + (c == 1 || c == 2));
                        p[(axis + 2) % 3] = (float)(v + (c >= 2));
                        q[c] = tu_add_vertex(s, p[0], p[1], p[2]);
                    }
                    tu_add_triangle(s, q[0], q[1], q[2]);
                    tu_add_triangle(s, q[0], q[2], q[3]);
                }
}

/* ---- the hooks: what each batch intersects, and in which order ----------- */

typedef struct batch_record {
    uint32_t point, place;
    uint64_t tag;
    brt_ray walked;
    uint32_t entry_voxel;
} batch_record;

typedef struct batch_log {
    batch_record *items;
    size_t count, cap;
    size_t clipped;             /* walks that start after their ray's tnear */
    const brt_ray *rays;        /* the traced rays, by tag */
} batch_log;

static void log_batch_ray(void *user, uint32_t point, uint32_t place, uint64_t tag, const brt_ray *ray,
                          uint32_t entry_voxel)
{
    batch_log *log = user;
    const uint64_t i = tag & ~BRT_TAG_OCCLUSION;
    if (log->count == log->cap) {
        log->cap = log->cap ? 2 * log->cap : 4096;
        log->items = realloc(log->items, log->cap * sizeof *log->items);
        if (!log->items) abort();
    }
    log->items[log->count].point = point;
    log->items[log->count].place = place;
    log->items[log->count].tag = tag;
    log->items[log->count].walked = *ray;
    log->items[log->count].entry_voxel = entry_voxel;
    log->count++;
    log->clipped += log->rays && ray->tnear > log->rays[i].tnear;
}

/* ---- the clip and the order change no byte -------------------------------- */

/* The uses: bit 0 clip, bit 1 order. */
static void set_uses(brt_trace_options *opt, int uses)
{
    opt->no_clip = !(uses & 1);
    opt->no_order = !(uses & 2);
}

/* Traces f's rays under opt (closest hits, then occlusion) against the
** reference; returns 0 after a failure. */
static int trace_equal(const fixture *f, const brt_trace_options *opt, brt_stats *stats, const char *what)
{
    brt_hit *hits = malloc(f->count * sizeof *hits);
    uint8_t *occ = malloc(f->count);
    brt_error err;
    size_t i;
    int ok = hits && occ;
    if (ok && brt_scene_trace(f->scene, opt, f->rays, f->count, hits, stats, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s: %s", what, err.message);
        ok = 0;
    }
    for (i = 0; ok && i < f->count; i++)
        if (memcmp(&hits[i], &f->want[i], sizeof *hits) != 0) {
            const brt_ray *r = &f->rays[i];
            test_fail_at(__FILE__, __LINE__, "%s: ray %zu (o %a %a %a d %a %a %a): t %a prim %u inst %u, "
                         "want t %a prim %u inst %u", what, i, r->org[0], r->org[1], r->org[2], r->dir[0],
                         r->dir[1], r->dir[2], hits[i].t, (unsigned)hits[i].prim, (unsigned)hits[i].inst,
                         f->want[i].t, (unsigned)f->want[i].prim, (unsigned)f->want[i].inst);
            ok = 0;
        }
    if (ok && brt_scene_occluded(f->scene, opt, f->rays, f->count, occ, NULL, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s, occlusion: %s", what, err.message);
        ok = 0;
    }
    for (i = 0; ok && i < f->count; i++)
        if (occ[i] != f->occluded[i]) {
            test_fail_at(__FILE__, __LINE__, "%s, occlusion: ray %zu occluded %d, want %d", what, i, occ[i],
                         f->occluded[i]);
            ok = 0;
        }
    free(hits);
    free(occ);
    return ok;
}

/* Every setting: in core with every ray queued (the paper's scheduler),
** out of core at a third of the blobs, in core with the proxies asked
** at points in memory (proxies_in_core); one thread and two; each use on
** and off.  With one thread, the clip must have moved some walks. */
static void sweep(const fixture *f)
{
    static const char *const settings[3] = {"in core, all queued", "a third of the blobs", "proxies in core"};
    brt_trace_options opt;
    brt_stats stats;
    batch_log log;
    char what[200];
    int setting, threads, uses;
    memset(&log, 0, sizeof log);
    log.rays = f->rays;
    for (setting = 0; setting < 3 && !test_failed(); setting++)
        for (threads = 1; threads <= 2 && !test_failed(); threads++)
            for (uses = 0; uses < 4 && !test_failed(); uses++) {
                memset(&opt, 0, sizeof opt);
                opt.threads = (unsigned)threads;
                opt.paper_scheduler = setting == 0;
                opt.proxies_in_core = setting == 2;
                if (setting == 1)
                    opt.memory_limit = f->scene->header.geometry_bytes / 3 + brt_svdag_memory_bytes(f->scene->dag);
                set_uses(&opt, uses);
                snprintf(what, sizeof what, "%s: %s, %d thread%s, clip %s, order %s", f->name, settings[setting],
                         threads, threads > 1 ? "s" : "", uses & 1 ? "on" : "off", uses & 2 ? "on" : "off");
                log.clipped = 0;
                brt_test_on_batch_ray(threads == 1 && uses == 3 ? log_batch_ray : NULL, &log);
                trace_equal(f, &opt, &stats, what);
                brt_test_on_batch_ray(NULL, NULL);
                EXPECT(setting != 2 || stats.proxy_tests > 0, "%s: no proxy was asked in core", what);
                EXPECT(threads > 1 || uses != 3 || setting == 2 || log.clipped > 0,
                       "%s: the clip moved no walk (%llu queued visits)", what,
                       (unsigned long long)stats.queued_visits);
                log.count = 0;
            }
    free(log.items);
}

static void test_soup(void)
{
    tu_scene s = {0};
    fixture f;
    uint64_t st = test_seed() + 5;
    tu_random_soup(&s, &st, 3000, 0.05f);
    if (plain_fixture(&f, "entry-soup.brs", &s, 200, 32, 600)) sweep(&f);
    fixture_free(&f);
    tu_scene_transform(&s, 1e4f, -3e4f);      /* far from the origin: g grows */
    if (plain_fixture(&f, "entry-soup-far.brs", &s, 300, 64, 300)) sweep(&f);
    fixture_free(&f);
    tu_scene_free(&s);
}

static void test_walls(void)
{
    tu_scene s = {0};
    fixture f;
    walls(&s);
    if (plain_fixture(&f, "entry-walls.brs", &s, 40, 16, 600)) sweep(&f);
    fixture_free(&f);
    tu_scene_free(&s);
}

static void test_instanced(void)
{
    fixture f;
    CHECK(instanced_fixture(&f, 300), "the instanced fixture could not be built");
    sweep(&f);
    fixture_free(&f);
}

/* ---- the clip: fewer nodes, never more -------------------------------------- */

/* The bottom level's BVH node visits with the clip and without, every ray
** queued, one thread, on a soup seen from everywhere: fewer in all.  (Not
** fewer for every ray: boxes a clipped walk starts inside all enter at its
** new tnear and are taken in slot order, not nearest first -- make
** bench-order shows it on the island.) */
static void test_fewer_nodes(void)
{
    tu_scene s = {0};
    fixture f;
    brt_trace_options opt;
    brt_stats stats;
    uint64_t st = test_seed() + 17, rays[2], nodes[2], r0, n0;
    double seconds;
    int clip;
    tu_random_soup(&s, &st, 6000, 0.04f);
    if (!plain_fixture(&f, "entry-nodes.brs", &s, 500, 32, 1500)) {
        fixture_free(&f);
        tu_scene_free(&s);
        return;
    }
    brt_test_count_bottom(1);
    for (clip = 0; clip < 2; clip++) {
        memset(&opt, 0, sizeof opt);
        opt.threads = 1;
        opt.paper_scheduler = 1;
        set_uses(&opt, clip);
        brt_test_bottom_level(&r0, &n0, &seconds);
        trace_equal(&f, &opt, &stats, clip ? "clip" : "no clip");
        brt_test_bottom_level(&rays[clip], &nodes[clip], &seconds);
        rays[clip] -= r0;
        nodes[clip] -= n0;
    }
    brt_test_count_bottom(0);
    EXPECT(rays[0] == rays[1] && rays[0] > 0, "batched rays %llu and %llu", (unsigned long long)rays[0],
           (unsigned long long)rays[1]);
    EXPECT(nodes[1] < nodes[0], "node visits with the clip %llu, without %llu", (unsigned long long)nodes[1],
           (unsigned long long)nodes[0]);
    printf("  entry: BVH nodes per batched ray %.2f without the clip, %.2f with it\n",
           (double)nodes[0] / (double)rays[0], (double)nodes[1] / (double)rays[1]);
    fixture_free(&f);
    tu_scene_free(&s);
}

/* ---- the order: the model's, and the walks untouched ---------------------- */

/* The model's key: the Morton code (x lowest) of the voxel of the point's
** proxy grid holding o + t d, t the walk's start (the entry: the clip is
** on), clamped into the grid, then the direction's octant (bit a: dir[a]
** negative).  Written with spread bits, apart from the library's loop. */
static uint64_t spread3(uint32_t v)
{
    uint64_t x = v & 0x3FFu;
    x = (x | x << 16) & 0x30000FFull;
    x = (x | x << 8) & 0x300F00Full;
    x = (x | x << 4) & 0x30C30C3ull;
    x = (x | x << 2) & 0x9249249ull;
    return x;
}

/* Where the proxy cast enters first over the ray's [tnear, tfar]: the
** least entry, also the one over [tnear, closest hit so far] when the ray
** was admitted with that hit, as each batch ray was. */
static float cast_entry(const brt_scene *scene, uint32_t point, const brt_ray *ray)
{
    float t = NAN;
    if (!brt_proxy_raycast(scene->dag, &scene->points[point].proxy, ray, ray->tnear, ray->tfar, &t)) t = NAN;
    return t;
}

static uint32_t model_voxel(const brt_scene *scene, uint32_t point, const brt_ray *ray)
{
    const brt_proxy *g = &scene->points[point].proxy;
    const double t = cast_entry(scene, point, ray);
    uint32_t v[3];
    int a;
    for (a = 0; a < 3; a++) {
        const double q = floor(((double)ray->org[a] + t * ray->dir[a] - g->origin[a]) / g->cell);
        v[a] = isnan(q) || q < 0 ? 0 : q > g->res - 1 ? g->res - 1 : (uint32_t)q;
    }
    return (uint32_t)(spread3(v[0]) | spread3(v[1]) << 1 | spread3(v[2]) << 2);
}

static uint64_t model_key(const brt_scene *scene, const brt_ray *rays, const batch_record *b)
{
    const float *d = rays[b->tag].dir;
    return (uint64_t)model_voxel(scene, b->point, &rays[b->tag]) << 3 |
           (uint64_t)((signbit(d[0]) != 0) | (signbit(d[1]) != 0) << 1 | (signbit(d[2]) != 0) << 2);
}

/* Records the finished calls' order. */
typedef struct finish_log {
    const brt_ray *rays;
    size_t count, next, done;
    uint64_t *order;
} finish_log;

static size_t finish_next(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    finish_log *l = user;
    size_t n = 0;
    while (n < max && l->next < l->count) {
        rays[n] = l->rays[l->next];
        tags[n++] = l->next++;
    }
    return n;
}

static void finish_done(void *user, const brt_ray *ray, const brt_hit *hit, const float normal[3],
                        uint32_t visits, uint64_t tag)
{
    finish_log *l = user;
    (void)ray; (void)hit; (void)normal; (void)visits;
    l->order[l->done++] = tag;
}

/* Stable: a batch's records sorted by the model's key, ties in queue
** order (insertion sort, the keys computed once). */
static void model_sort(const brt_scene *scene, const brt_ray *rays, batch_record *b, size_t n)
{
    uint64_t *keys = malloc(n * sizeof *keys);
    size_t i, j;
    if (!keys) abort();
    for (i = 0; i < n; i++) {
        batch_record x = b[i];
        const uint64_t k = model_key(scene, rays, &x);
        for (j = i; j > 0 && keys[j - 1] > k; j--) {
            b[j] = b[j - 1];
            keys[j] = keys[j - 1];
        }
        b[j] = x;
        keys[j] = k;
    }
    free(keys);
}

/* Traces f's rays as a stream under the uses given (one thread, a limit
** that makes loads repeat), logging each batch ray and the finished calls. */
static int logged_trace(const fixture *f, int uses, batch_log *log, finish_log *fin)
{
    brt_trace_options opt;
    brt_ray_source source;
    brt_error err;
    brt_result r;
    memset(log, 0, sizeof *log);
    memset(fin, 0, sizeof *fin);
    fin->rays = f->rays;
    fin->count = f->count;
    fin->order = malloc(f->count * sizeof *fin->order);
    memset(&opt, 0, sizeof opt);
    opt.threads = 1;
    opt.memory_limit = f->scene->header.geometry_bytes / 3 + brt_svdag_memory_bytes(f->scene->dag);
    opt.rays_in_flight = 2000;
    set_uses(&opt, uses);
    source.next_rays = finish_next;
    source.finished = finish_done;
    source.user = fin;
    brt_test_on_batch_ray(log_batch_ray, log);
    r = fin->order ? brt_scene_trace_stream(f->scene, &opt, &source, NULL, &err) : BRT_ENOMEM;
    brt_test_on_batch_ray(NULL, NULL);
    if (r != BRT_OK) test_fail_at(__FILE__, __LINE__, "uses %d: trace failed", uses);
    return r == BRT_OK && fin->done == f->count;
}

/* With the order off a batch is intersected in queue order; with it on,
** clipped or not, in that order sorted stably by the model's key: the
** same rays, batch by batch, and the same finished calls in the same
** order.  The clipped walk starts where the cast enters, bit for bit, and
** the entry voxel the library keeps is the model's.  Proxies of 256^3:
** keys of 27 bits, which take all three passes of the radix sort. */
static void test_order_model(void)
{
    tu_scene s = {0};
    fixture f;
    batch_log logs[3];          /* order off, clip on; order on, clip on; order on, clip off */
    finish_log fin[3];
    static const int uses[3] = {1, 3, 2};
    uint64_t st = test_seed() + 23;
    size_t i, start, batches = 0, moved = 0;
    int k;
    memset(logs, 0, sizeof logs);
    memset(fin, 0, sizeof fin);
    tu_random_soup(&s, &st, 3000, 0.06f);
    if (!plain_fixture(&f, "entry-order.brs", &s, 150, 256, 500)) {
        fixture_free(&f);
        tu_scene_free(&s);
        return;
    }
    /* Half the rays' zero direction components negative: -0 is in the
    ** octant of its sign bit (the same rays, the same hits). */
    for (i = 0; i < f.count; i += 2)
        for (k = 0; k < 3; k++)
            if (f.rays[i].dir[k] == 0.0f) f.rays[i].dir[k] = -0.0f;
    for (k = 0; k < 3; k++)
        if (!logged_trace(&f, uses[k], &logs[k], &fin[k])) goto done;
    for (k = 1; k < 3; k++) {
        EXPECT(memcmp(fin[0].order, fin[k].order, f.count * sizeof *fin[0].order) == 0,
               "uses %d: the order of the finished calls changed", uses[k]);
        CHECK(logs[0].count == logs[k].count, "%zu batch rays with the order off, %zu with uses %d",
              logs[0].count, logs[k].count, uses[k]);
    }
    for (i = 0; i < logs[1].count && !test_failed(); i++) {
        const batch_record *b = &logs[1].items[i];
        const float t = cast_entry(f.scene, b->point, &f.rays[b->tag]);
        EXPECT(t == b->walked.tnear, "batch ray %zu (tag %llu) at point %u: its walk starts at %a, the "
               "proxy cast enters at %a", i, (unsigned long long)b->tag, b->point, b->walked.tnear, t);
        EXPECT(b->entry_voxel == model_voxel(f.scene, b->point, &f.rays[b->tag]),
               "batch ray %zu (tag %llu): entry voxel %u, the model's %u", i, (unsigned long long)b->tag,
               b->entry_voxel, model_voxel(f.scene, b->point, &f.rays[b->tag]));
    }
    for (start = 0; start < logs[0].count && !test_failed(); batches++) {
        size_t end = start + 1;
        while (end < logs[0].count && logs[0].items[end].place != 0) end++;
        model_sort(f.scene, f.rays, logs[0].items + start, end - start);
        for (i = start; i < end && !test_failed(); i++) {
            moved += logs[0].items[i].place != i - start;
            for (k = 1; k < 3; k++)
                EXPECT(logs[k].items[i].tag == logs[0].items[i].tag && logs[k].items[i].point == logs[0].items[i].point,
                       "uses %d, batch %zu at point %u, place %zu: tag %llu intersected, the model's stable sort "
                       "puts %llu there", uses[k], batches, logs[k].items[i].point, i - start,
                       (unsigned long long)logs[k].items[i].tag, (unsigned long long)logs[0].items[i].tag);
        }
        start = end;
    }
    EXPECT(batches > 10 && moved > logs[0].count / 4, "%zu batches, %zu of %zu rays moved by the sort: the "
           "test would not see a wrong order", batches, moved, logs[0].count);
done:
    for (k = 0; k < 3; k++) {
        free(logs[k].items);
        free(fin[k].order);
    }
    fixture_free(&f);
    tu_scene_free(&s);
}

void suite_entry(void)
{
    test_run("entry: clip and order change no byte: a soup, near and far from the origin", test_soup);
    test_run("entry: clip and order change no byte: walls in voxel planes, grazing rays", test_walls);
    test_run("entry: clip and order change no byte: instances sheared, mirrored", test_instanced);
    test_run("entry: the clip visits fewer BVH nodes in all on a soup", test_fewer_nodes);
    test_run("entry: the order is the model's stable sort; walks and finished calls keep theirs",
             test_order_model);
}
