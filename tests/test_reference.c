/*
** tests/test_reference.c -- schedule_reference, the paper's loop written
** as one function (batchrt.c; brt_trace_options.reference), against the
** layered scheduler with its layers off: paper_scheduler, one thread,
** no_inner, no_decode, the rays in flight given.
**
** Equal hits alone would not show two loops deciding apart (any schedule
** gives the direct mode's hits), so each trace is observed from outside:
** every read the geometry cache makes goes through brt_trace_options
** .read_fn and is logged (offset and size: which blob, in which order;
** one thread reads no blob ahead), and a stream source logs every
** finished call in order (tag, hit, normal, visits).  Both logs and every
** count of the statistics must be equal, byte for byte.  The source
** behaves as a path tracer: a closest-hit ray that hits sends a new ray
** from its hit point, every other one an occlusion ray, so the queues
** mix both kinds and the rays in flight change with the schedule.
**
** Each scene and setting must give the comparison something to see, or
** the test fails: reloads (a memory limit that forces evictions), culls,
** occluded rays, prototypes loaded; the reference's closest hits of the
** first rays are brute force's (tu_brute_force), so the two loops cannot
** agree on a wrong answer.
*/
#include "test.h"
#include "util.h"

#include <math.h>
#include <stddef.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#define MAX_READS 20000

typedef struct read_log {       /* the cache's reads, in order */
    uint64_t offset[MAX_READS], size[MAX_READS];
    uint32_t count;
} read_log;

typedef struct finish {         /* one finished call */
    uint64_t tag;
    brt_hit hit;
    float normal[3];
    uint32_t visits;
} finish;

typedef struct bouncing {       /* the source: first rays, then follow-ups */
    const brt_ray *rays;
    uint32_t count, next;
    brt_ray *pending;           /* follow-up rays, first in first out */
    uint64_t *pending_tags;
    uint32_t head, tail;
    finish *log;                /* 2 * count at most */
    uint32_t finished;
} bouncing;

static long logged_read(int fd, void *buf, size_t size, uint64_t offset, void *user)
{
    read_log *log = user;
    if (log->count < MAX_READS) {       /* more: a failure (compare) */
        log->offset[log->count] = offset;
        log->size[log->count] = size;
        log->count++;
    }
    return (long)pread(fd, buf, size, (off_t)offset);
}

/* The offset of read i, 0 past the log's end. */
static uint64_t read_at(const read_log *log, uint32_t i)
{
    return i < log->count && i < MAX_READS ? log->offset[i] : 0;
}

static size_t bouncing_next(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    bouncing *b = user;
    size_t n = 0;
    for (; n < max && b->head < b->tail; n++, b->head++) {
        rays[n] = b->pending[b->head];
        tags[n] = b->pending_tags[b->head];
    }
    for (; n < max && b->next < b->count; n++, b->next++) {
        rays[n] = b->rays[b->next];
        tags[n] = b->next | (b->next % 4 == 3 ? BRT_TAG_OCCLUSION : 0);
    }
    return n;
}

/* A first closest-hit ray that hits sends one more from its hit point,
** turned a quarter about z and tilted; every other one asks occlusion. */
static void bouncing_finished(void *user, const brt_ray *ray, const brt_hit *hit, const float normal[3],
                              uint32_t visits, uint64_t tag)
{
    bouncing *b = user;
    finish *f = &b->log[b->finished++];
    memset(f, 0, sizeof *f);
    f->tag = tag;
    f->hit = *hit;
    memcpy(f->normal, normal, sizeof f->normal);
    f->visits = visits;
    if (tag < b->count && hit->prim != BRT_NO_PRIM) {
        brt_ray *r = &b->pending[b->tail];
        int a;
        for (a = 0; a < 3; a++) r->org[a] = ray->org[a] + hit->t * ray->dir[a];
        r->dir[0] = -ray->dir[1];
        r->dir[1] = ray->dir[0];
        r->dir[2] = 0.5f * ray->dir[2] + 0.25f;
        r->tnear = 1e-3f;
        r->tfar = INFINITY;
        b->pending_tags[b->tail++] = (b->count + tag) | (tag % 2 ? BRT_TAG_OCCLUSION : 0);
    }
}

typedef struct run {
    read_log reads;
    finish *log;
    uint32_t finished;
    brt_stats stats;
} run;

/* One trace of rays[0..count) through the bouncing source; 0 on error. */
static int trace_run(brt_scene *scene, const brt_trace_options *base, int reference, const brt_ray *rays,
                     uint32_t count, run *out)
{
    brt_trace_options opt = *base;
    brt_ray_source source;
    bouncing b;
    brt_error err;
    brt_result r;
    memset(&b, 0, sizeof b);
    b.rays = rays;
    b.count = count;
    b.pending = malloc(count * sizeof *b.pending);
    b.pending_tags = malloc(count * sizeof *b.pending_tags);
    b.log = out->log;
    out->reads.count = 0;
    opt.reference = reference;
    opt.read_fn = logged_read;
    opt.read_user = &out->reads;
    source.next_rays = bouncing_next;
    source.finished = bouncing_finished;
    source.user = &b;
    r = b.pending && b.pending_tags ? brt_scene_trace_stream(scene, &opt, &source, &out->stats, &err) : BRT_ENOMEM;
    out->finished = b.finished;
    free(b.pending);
    free(b.pending_tags);
    if (r != BRT_OK) test_fail_at(__FILE__, __LINE__, "%s trace: %s", reference ? "reference" : "layered",
                                  r == BRT_ENOMEM ? "out of memory" : err.message);
    return r == BRT_OK;
}

/* The counts of brt_stats that a schedule decides (not the times, and
** not layer 7's shadow loads, which the reference leaves 0). */
#define STAT(field) {#field, offsetof(brt_stats, field)}
static const struct { const char *name; size_t at; } counts[] = {
    STAT(rays), STAT(batching_points), STAT(geometry_bytes), STAT(disk_bytes_read), STAT(batch_loads),
    STAT(cache_peak_bytes), STAT(memory_limit), STAT(proxy_bytes), STAT(proxy_tests), STAT(proxy_culled),
    STAT(visits), STAT(queued_visits), STAT(resident_visits), STAT(oversized_loads), STAT(occlusion_rays),
    STAT(occlusion_hits), STAT(occlusion_inner_stopped), STAT(prototype_loads), STAT(decoded_bytes)};

static uint64_t count_of(const brt_stats *s, size_t k)
{
    uint64_t v;
    memcpy(&v, (const unsigned char *)s + counts[k].at, sizeof v);
    return v;
}

/* What the settings of a scene showed, for the checks that the
** comparison had something to compare. */
typedef struct seen {
    uint64_t reloads, culled, occluded, prototype_loads, oversized;
} seen;

static void print_finish(const char *who, const run *r, uint32_t i)
{
    const finish *f = &r->log[i];
    if (i < r->finished)
        printf("  %s: tag %llu t %a prim %u inst %u visits %u\n", who, (unsigned long long)f->tag, f->hit.t,
               (unsigned)f->hit.prim, (unsigned)f->hit.inst, (unsigned)f->visits);
}

/* The reference and the layered loop under one setting: equal reads,
** finished calls and counts. */
static void compare(brt_scene *scene, const brt_trace_options *opt, const brt_ray *rays, uint32_t count,
                    const char *what, seen *saw)
{
    static run ref, lay;
    uint32_t i, j, distinct = 0;
    size_t k;
    ref.log = malloc(2 * (size_t)count * sizeof *ref.log);
    lay.log = malloc(2 * (size_t)count * sizeof *lay.log);
    if (!ref.log || !lay.log) {
        test_fail_at(__FILE__, __LINE__, "out of memory");
    } else if (trace_run(scene, opt, 1, rays, count, &ref) && trace_run(scene, opt, 0, rays, count, &lay)) {
        for (i = 0; i < ref.reads.count && i < lay.reads.count && i < MAX_READS; i++)
            if (ref.reads.offset[i] != lay.reads.offset[i] || ref.reads.size[i] != lay.reads.size[i]) break;
        EXPECT(ref.reads.count == lay.reads.count && i == ref.reads.count && i < MAX_READS,
               "%s: the reference read %u times, the layered loop %u; first difference at read %u "
               "(offsets %llu and %llu)", what, (unsigned)ref.reads.count, (unsigned)lay.reads.count, (unsigned)i,
               (unsigned long long)read_at(&ref.reads, i), (unsigned long long)read_at(&lay.reads, i));
        for (i = 0; i < ref.finished && i < lay.finished; i++) {
            const finish *a = &ref.log[i], *b = &lay.log[i];
            if (a->tag != b->tag || memcmp(&a->hit, &b->hit, sizeof a->hit) ||
                memcmp(a->normal, b->normal, sizeof a->normal) || a->visits != b->visits)
                break;
        }
        if (ref.finished != lay.finished || i < ref.finished) {
            test_fail_at(__FILE__, __LINE__, "%s: %u and %u finished calls, first difference at %u", what,
                         (unsigned)ref.finished, (unsigned)lay.finished, (unsigned)i);
            print_finish("reference", &ref, i);
            print_finish("layered  ", &lay, i);
        }
        for (k = 0; k < sizeof counts / sizeof *counts; k++)
            EXPECT(count_of(&ref.stats, k) == count_of(&lay.stats, k), "%s: %s %llu in the reference, %llu in "
                   "the layered loop", what, counts[k].name, (unsigned long long)count_of(&ref.stats, k),
                   (unsigned long long)count_of(&lay.stats, k));
        for (i = 0; i < ref.reads.count && i < MAX_READS; i++) {
            for (j = 0; j < i && ref.reads.offset[j] != ref.reads.offset[i]; j++) {}
            distinct += j == i;
        }
        saw->reloads += ref.reads.count - distinct;
        saw->culled += ref.stats.proxy_culled;
        saw->occluded += ref.stats.occlusion_hits;
        saw->prototype_loads += ref.stats.prototype_loads;
        saw->oversized += ref.stats.oversized_loads;
    }
    free(ref.log);
    free(lay.log);
}

/* Every setting of one scene: proxies on and off; no limit, a third of
** the blobs' bytes (evictions), and one byte (each load held alone, a
** point of instances with its prototypes); few rays in flight and all.
** every_blob: the bytes of all blobs, as the cache charges them; the
** proxies' bytes come out of the limit when they are on. */
static void compare_settings(brt_scene *scene, const brt_ray *rays, uint32_t count, uint64_t every_blob,
                             uint64_t proxy_bytes, const char *name, seen *saw)
{
    const uint64_t budgets[3] = {0, every_blob / 3, 1};
    const uint32_t in_flight[2] = {37, 2 * count};
    int no_proxy;
    size_t l, f;
    for (no_proxy = 0; no_proxy < 2; no_proxy++)
        for (l = 0; l < 3; l++)
            for (f = 0; f < 2 && !test_failed(); f++) {
                const uint64_t limit = budgets[l] && !no_proxy ? proxy_bytes + budgets[l] : budgets[l];
                brt_trace_options opt;
                char what[160];
                memset(&opt, 0, sizeof opt);
                opt.paper_scheduler = 1;        /* layers 1 and 4 off */
                opt.threads = 1;                /* 4 and 5 */
                opt.no_inner = 1;               /* 7 */
                opt.no_decode = 1;              /* 9 */
                opt.rays_in_flight = in_flight[f];   /* 10 */
                opt.no_proxy = no_proxy;
                opt.memory_limit = limit;
                snprintf(what, sizeof what, "%s, proxies %s, limit %llu, %u in flight", name,
                         no_proxy ? "off" : "on", (unsigned long long)limit, (unsigned)in_flight[f]);
                compare(scene, &opt, rays, count, what, saw);
            }
}

/* The bytes of every blob and of the proxies, from a reference run
** without a limit that reaches every batching point. */
static int measure(brt_scene *scene, const brt_ray *rays, uint32_t count, uint64_t *every_blob,
                   uint64_t *proxy_bytes)
{
    brt_trace_options opt;
    brt_stats stats;
    brt_error err;
    brt_hit *hits = malloc(count * sizeof *hits);
    brt_result r;
    memset(&opt, 0, sizeof opt);
    opt.reference = 1;
    r = hits ? brt_scene_trace(scene, &opt, rays, count, hits, &stats, &err) : BRT_ENOMEM;
    free(hits);
    if (r != BRT_OK) return 0;
    *every_blob = stats.cache_peak_bytes;
    *proxy_bytes = stats.proxy_bytes;
    return stats.batch_loads == stats.batching_points && stats.batching_points > 4;
}

/* A soup of triangles, 3000 rays of every kind. */
static void test_triangles(void)
{
    enum { N = 3000 };
    tu_scene s;
    brt_scene *scene;
    brt_ray *rays = malloc(N * sizeof *rays);
    brt_hit *hits = malloc(N * sizeof *hits);
    brt_trace_options opt;
    brt_hit want;
    brt_error err;
    uint64_t st = test_seed() + 4001, every_blob = 0, proxy_bytes = 0;
    float lo[3], hi[3];
    seen saw;
    uint32_t i;
    memset(&s, 0, sizeof s);
    memset(&saw, 0, sizeof saw);
    tu_random_soup(&s, &st, 3000, 0.05f);
    tu_scene_bounds(&s, lo, hi);
    scene = tu_build_scene(&s, 150, 16, 1, tu_scratch("reference.brs"));
    CHECK(scene && rays && hits, "set-up failed");
    for (i = 0; i < N; i++) tu_make_ray(&s, lo, hi, (int)(i % TU_RAY_KINDS), &st, &rays[i]);
    /* The reference against brute force. */
    memset(&opt, 0, sizeof opt);
    opt.reference = 1;
    opt.memory_limit = 1;
    CHECK(brt_scene_trace(scene, &opt, rays, N, hits, NULL, &err) == BRT_OK, "%s", err.message);
    for (i = 0; i < N; i++) {
        brt_hit_clear(&want);
        tu_brute_force(&s, NULL, &rays[i], &want);
        if (memcmp(&want, &hits[i], sizeof want)) break;
    }
    CHECK(i == N, "ray %u: the reference's t %a prim %u, brute force's t %a prim %u", (unsigned)i, hits[i].t,
          (unsigned)hits[i].prim, want.t, (unsigned)want.prim);
    CHECK(measure(scene, rays, N, &every_blob, &proxy_bytes), "the rays must reach every batching point");
    compare_settings(scene, rays, N, every_blob, proxy_bytes, "triangles", &saw);
    EXPECT(saw.reloads > 0 && saw.culled > 0 && saw.occluded > 0 && saw.oversized > 0,
           "nothing to compare: %llu reloads, %llu culls, %llu occluded rays, %llu oversized loads",
           (unsigned long long)saw.reloads, (unsigned long long)saw.culled, (unsigned long long)saw.occluded,
           (unsigned long long)saw.oversized);
    brt_scene_close(scene);
    tu_scene_free(&s);
    free(rays);
    free(hits);
}

/* An instanced scene: a world soup and 40 instances of three prototypes
** (rotated about z, scaled, moved), in points of world triangles and
** points of instances that use several prototypes each; 3000 rays. */
static void test_instances(void)
{
    enum { N = 3000 };
    tu_instanced s;
    brt_scene_source source;
    brt_scene_options sopt;
    brt_scene *scene = NULL;
    brt_ray *rays = malloc(N * sizeof *rays);
    brt_error err;
    uint64_t st = test_seed() + 4002, every_blob = 0, proxy_bytes = 0;
    const float lo[3] = {0, 0, 0}, hi[3] = {8, 8, 8};
    seen saw;
    uint32_t i, p;
    memset(&s, 0, sizeof s);
    memset(&saw, 0, sizeof saw);
    tu_random_soup(&s.world, &st, 400, 0.05f);
    tu_scene_transform(&s.world, 8.0f, 0.0f);
    s.proto_count = 3;
    for (p = 0; p < 3; p++) tu_random_soup(&s.protos[p], &st, 40 + 30 * p, 0.3f);
    for (i = 0; i < 40; i++) {
        const float a = tu_rnd(&st, 0, 6.2831853f), k = tu_rnd(&st, 0.5f, 1.5f);
        const float xf[12] = {k * cosf(a), -k * sinf(a), 0, tu_rnd(&st, 0, 7),
                              k * sinf(a), k * cosf(a), 0, tu_rnd(&st, 0, 7),
                              0, 0, k, tu_rnd(&st, 0, 7)};
        tu_add_instance(&s, i % 3, xf);
    }
    tu_instanced_source(&s, &source);
    memset(&sopt, 0, sizeof sopt);
    sopt.point_tris = 100;
    sopt.proxy_res = 16;
    sopt.point_instanced = 600;
    sopt.threads = 1;
    if (brt_scene_build_source(&source, &sopt, 1, tu_scratch("reference-inst.brs"), &err) != BRT_OK ||
        brt_scene_open(tu_scratch("reference-inst.brs"), &scene, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "reference-inst.brs: %s", err.message);
        tu_instanced_free(&s);
        free(rays);
        return;
    }
    CHECK(rays, "out of memory");
    for (i = 0; i < N; i++) tu_make_ray(&s.world, lo, hi, (int)(i % TU_RAY_KINDS), &st, &rays[i]);
    CHECK(measure(scene, rays, N, &every_blob, &proxy_bytes), "the rays must reach every batching point");
    compare_settings(scene, rays, N, every_blob, proxy_bytes, "instances", &saw);
    /* 12 settings, 3 prototypes: more loads than 36 are reloads. */
    EXPECT(saw.reloads > 0 && saw.culled > 0 && saw.occluded > 0 && saw.prototype_loads > 3 * 12 &&
           saw.oversized > 0,
           "nothing to compare: %llu reloads, %llu culls, %llu occluded rays, %llu prototype loads, "
           "%llu oversized loads", (unsigned long long)saw.reloads, (unsigned long long)saw.culled,
           (unsigned long long)saw.occluded, (unsigned long long)saw.prototype_loads,
           (unsigned long long)saw.oversized);
    brt_scene_close(scene);
    tu_instanced_free(&s);
    free(rays);
}

void suite_reference(void)
{
    test_run("reference: the paper's loop == the layered loop, triangles", test_triangles);
    test_run("reference: the paper's loop == the layered loop, instances", test_instances);
}
