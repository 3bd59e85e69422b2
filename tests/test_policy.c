/*
** tests/test_policy.c -- the scheduler's and the geometry cache's policies
** against a model written apart from batchrt.c (issue 32, class 2).
**
** Hits byte-equal to the direct mode do not pin which batching point is
** loaded when: a cache that evicts the wrong entry, a scheduler that
** serves the wrong queue or a proxy test over the wrong segment all give
** the same hits, only more loads.  So this file simulates the method as
** the paper states it -- Pharr et al.'s scheduler (the fullest queue
** first, ties to the lowest id; rays queued at each batching point whose
** box they enter before their closest hit and whose proxy they hit), an
** LRU cache of page-rounded blobs within the memory limit less the
** proxies' bytes, and batchrt's layers 4 (resident points intersected at
** once, touching the LRU order), 2 (no proxies when the budget holds
** every blob) and 9 (a point decoded at its load when the budget holds
** its layout beside every blob and the layouts made so far) -- and
** compares the sequence of loads, read through
** brt_trace_options.read_fn (one thread: no read-ahead), and the counts.
**
** The scenes are made so that the model needs no proxy of its own: one
** triangle per batching point, rays along +x, and every ray kept only
** when each question the method asks has a clear answer -- the ray's
** (y, z) at least 4 proxy cells inside or outside each triangle's
** shadow along x (a proxy cell holds the triangle or lies at least a
** cell from it, so a ray 4 cells off passes no set cell), 0.02 from each
** box's side, and the crossings of the triangles' planes and the boxes'
** entries apart along the ray (the triangles tilt at most 60 degrees from
** the yz plane, so a crossing 8 cells past the segment's end leaves the
** segment at least 4 cells from the triangle).
**
** And the gate of a point of instances' proxy (proxy_admits): rays near
** enough are cast and culled, rays from far away admitted untested,
** counted against the number made so by construction.
*/
#include "test.h"
#include "util.h"

#include <fcntl.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#define NP 8            /* triangles, each its own batching point */
#define NR 256          /* rays */
#define MAX_LOADS 4096
/* The resident layout of a one-triangle BVH (bvh.c): one node of 128
** bytes and one block of four triangles of 160. */
#define DECODED_BYTES (128 + 160)

typedef struct point_info {     /* a batching point, from the scene file */
    float lo[3], hi[3], cell;
    uint64_t offset, bytes;     /* blob place; bytes page-rounded */
    uint32_t tri;               /* its triangle (the one at x = 2.5 tri) */
} point_info;

typedef struct ray_view {       /* what a ray meets at each point */
    int inbox[NP], inside[NP];
    double cross[NP];           /* t where it crosses the point's plane */
} ray_view;

typedef struct policy_scene {
    tu_scene tris;
    brt_scene *scene;
    point_info pts[NP];
    uint32_t by_tri[NP];        /* the point of each triangle */
    uint64_t proxy_bytes, all_bytes;
    brt_ray rays[NR];
    ray_view views[NR];
    uint32_t ray_count;
} policy_scene;

typedef struct load_log {       /* the library's loads, in order */
    const policy_scene *ps;
    uint32_t ids[MAX_LOADS];
    uint32_t count;
} load_log;

/* ---- the scene ---------------------------------------------------------- */

/* Triangle i: a well-shaped triangle about a random centre in [2, 6]^2,
** in the plane x = 2.5 i, or tilted up to +3 along x (at most 60 degrees). */
static void make_triangles(tu_scene *s, uint64_t *st)
{
    uint32_t i;
    int k;
    for (i = 0; i < NP; i++) {
        const double cy = tu_rnd(st, 2, 6), cz = tu_rnd(st, 2, 6), a0 = tu_rnd(st, 0, 6.2831853f);
        double y[3], z[3], x[3], w = brt_random_float(st) < 0.5f ? 0.0 : tu_rnd(st, 1, 3);
        uint32_t v[3];
        for (k = 0; k < 3; k++) {
            const double a = a0 + 2.0943951 * k + tu_rnd(st, -0.3f, 0.3f), r = tu_rnd(st, 2, 3);
            y[k] = cy + r * cos(a);
            z[k] = cz + r * sin(a);
        }
        for (;;) {      /* flatten until the normal is within 60 degrees of x */
            double e1[3], e2[3], n[3];
            x[0] = 2.5 * i;
            x[1] = 2.5 * i + w;
            x[2] = 2.5 * i + w * 0.5;
            e1[0] = x[1] - x[0]; e1[1] = y[1] - y[0]; e1[2] = z[1] - z[0];
            e2[0] = x[2] - x[0]; e2[1] = y[2] - y[0]; e2[2] = z[2] - z[0];
            n[0] = e1[1] * e2[2] - e1[2] * e2[1];
            n[1] = e1[2] * e2[0] - e1[0] * e2[2];
            n[2] = e1[0] * e2[1] - e1[1] * e2[0];
            if (fabs(n[0]) >= 0.5 * sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])) break;
            w *= 0.5;
        }
        for (k = 0; k < 3; k++) v[k] = tu_add_vertex(s, (float)x[k], (float)y[k], (float)z[k]);
        tu_add_triangle(s, v[0], v[1], v[2]);
    }
}

static float le_f32(const unsigned char *p)
{
    uint32_t w = brt_get_le32(p);
    float f;
    memcpy(&f, &w, 4);
    return f;
}

/* The batching points' boxes, cells and blobs from the scene file
** (README's layout: the point table at the header's first section,
** 80-byte entries); each point is matched to its triangle by its box's
** lowest x, 2.5 times the triangle's number. */
static int read_points(policy_scene *ps, const char *path)
{
    size_t size;
    unsigned char *f = tu_slurp(path, &size);
    uint32_t j, seen = 0;
    int a, ok = f && size >= 256 && brt_get_le32(f + 32) == NP;
    for (j = 0; ok && j < NP; j++) {
        const unsigned char *e = f + brt_get_le64(f + 56) + 80u * j;
        point_info *p = &ps->pts[j];
        for (a = 0; a < 3; a++) {
            p->lo[a] = le_f32(e + 4 * a);
            p->hi[a] = le_f32(e + 12 + 4 * a);
        }
        p->offset = brt_get_le64(e + 24);
        p->bytes = (brt_get_le64(e + 32) + 4095) / 4096 * 4096;
        p->cell = le_f32(e + 72);
        ps->all_bytes += p->bytes;
        p->tri = (uint32_t)(p->lo[0] / 2.5f);
        ok = p->tri < NP && p->lo[0] == (float)(2.5 * p->tri) && p->cell > 0 && !(seen >> p->tri & 1);
        seen |= 1u << p->tri;
    }
    free(f);
    for (j = 0; ok && j < NP; j++) ps->by_tri[ps->pts[j].tri] = j;
    return ok;
}

/* Signed distance of (y, z) from triangle t's shadow along x (positive
** inside), and the x where the ray at (y, z) crosses its plane. */
static double shadow_distance(const tu_scene *s, uint32_t t, double y, double z, double *x)
{
    const float *v[3];
    double area, d = INFINITY, b[3];
    int k;
    for (k = 0; k < 3; k++) v[k] = tu_vertex(s, t, k);
    area = (v[1][1] - v[0][1]) * (v[2][2] - v[0][2]) - (v[1][2] - v[0][2]) * (v[2][1] - v[0][1]);
    for (k = 0; k < 3; k++) {
        const float *p = v[(k + 1) % 3], *q = v[(k + 2) % 3];
        const double ey = q[1] - p[1], ez = q[2] - p[2];
        const double cross = ey * (z - p[2]) - ez * (y - p[1]);
        b[k] = cross / area;
        d = fmin(d, (area > 0 ? cross : -cross) / sqrt(ey * ey + ez * ez));
    }
    *x = b[0] * v[0][0] + b[1] * v[1][0] + b[2] * v[2][0];
    return d;
}

/* What ray (y, z) meets; 0 when some question has no clear answer. */
static int view_ray(const policy_scene *ps, double y, double z, ray_view *v)
{
    uint32_t j, k;
    for (j = 0; j < NP; j++) {
        const point_info *p = &ps->pts[j];
        const double side = fmin(fmin(y - p->lo[1], p->hi[1] - y), fmin(z - p->lo[2], p->hi[2] - z));
        const double d = shadow_distance(&ps->tris, p->tri, y, z, &v->cross[j]);
        if (fabs(side) < 0.02 || fabs(d) < 4 * p->cell) return 0;
        v->inbox[j] = side > 0;
        v->inside[j] = d > 0;
        v->cross[j] += 1.0;     /* the origin's x is -1, the direction +x */
    }
    for (j = 0; j < NP; j++)
        for (k = 0; k < NP; k++) {
            if (j == k || !v->inside[k]) continue;
            if (v->inside[j] && fabs(v->cross[j] - v->cross[k]) < 8 * fmax(ps->pts[j].cell, ps->pts[k].cell))
                return 0;
            if (v->inbox[j] && fabs(ps->pts[j].lo[0] + 1.0 - v->cross[k]) < 0.05) return 0;
        }
    return 1;
}

static int policy_scene_make(policy_scene *ps, const char *name)
{
    uint64_t st = test_seed() + 32;
    int tries = 0;
    memset(ps, 0, sizeof *ps);
    make_triangles(&ps->tris, &st);
    ps->scene = tu_build_scene(&ps->tris, 1, 128, 1, tu_scratch(name));
    if (!ps->scene || !read_points(ps, tu_scratch(name))) return 0;
    while (ps->ray_count < NR && tries++ < 100 * NR) {
        const double y = tu_rnd(&st, 0, 8), z = tu_rnd(&st, 0, 8);
        brt_ray r = {{-1, 0, 0}, {1, 0, 0}, 0.0f, INFINITY};
        r.org[1] = (float)y;
        r.org[2] = (float)z;
        if (!view_ray(ps, r.org[1], r.org[2], &ps->views[ps->ray_count])) continue;
        ps->rays[ps->ray_count++] = r;
    }
    return ps->ray_count == NR;
}

static void policy_scene_free(policy_scene *ps)
{
    brt_scene_close(ps->scene);
    tu_scene_free(&ps->tris);
}

/* ---- the model ------------------------------------------------------------ */

typedef struct model {
    const policy_scene *ps;
    int paper, proxies;
    uint64_t budget, held, peak, decoded;
    int resident[NP], decode[NP];
    uint32_t lru[NP], lru_count;        /* least recently used first */
    uint32_t queue[NP][NR], queued[NP];
    double hit[NR];
    int last[NR];                       /* the walk's step (triangle), -1: none */
    uint32_t free_slots, next_ray;
    uint32_t loads[MAX_LOADS], load_count;
    uint64_t proxy_tests, proxy_culled, queued_visits, resident_visits;
} model;

static void lru_remove(model *m, uint32_t id)
{
    uint32_t i, k = 0;
    for (i = 0; i < m->lru_count; i++)
        if (m->lru[i] != id) m->lru[k++] = m->lru[i];
    m->lru_count = k;
}

static void lru_push(model *m, uint32_t id)
{
    lru_remove(m, id);
    m->lru[m->lru_count++] = id;
}

static void meet(model *m, uint32_t ray, uint32_t id)
{
    const ray_view *v = &m->ps->views[ray];
    if (v->inside[id] && v->cross[id] < m->hit[ray]) m->hit[ray] = v->cross[id];
}

/* The walk from the box entered at step last[ray] on, in order of box
** entry (triangle k's box is entered at t = 2.5 k + 1): returns the
** point it is queued at, or -1 (finished). */
static int walk(model *m, uint32_t ray)
{
    const ray_view *v = &m->ps->views[ray];
    uint32_t k;
    for (k = (uint32_t)(m->last[ray] + 1); k < NP; k++) {
        const uint32_t id = m->ps->by_tri[k];
        if (!v->inbox[id] || m->ps->pts[id].lo[0] + 1.0 > m->hit[ray]) continue;
        m->last[ray] = (int)k;
        if (!m->paper && m->resident[id]) {            /* layer 4 */
            lru_push(m, id);
            m->resident_visits++;
            meet(m, ray, id);
            continue;
        }
        if (m->proxies) {
            m->proxy_tests++;
            if (!(v->inside[id] && v->cross[id] <= m->hit[ray])) {
                m->proxy_culled++;
                continue;
            }
        }
        m->queue[id][m->queued[id]++] = ray;
        m->queued_visits++;
        return (int)id;
    }
    return -1;
}

static void refill(model *m)
{
    while (m->free_slots > 0 && m->next_ray < m->ps->ray_count) {
        uint32_t n = m->ps->ray_count - m->next_ray, i;
        if (n > m->free_slots) n = m->free_slots;
        m->free_slots -= n;
        for (i = 0; i < n; i++, m->next_ray++) {
            m->hit[m->next_ray] = INFINITY;
            m->last[m->next_ray] = -1;
            if (walk(m, m->next_ray) < 0) m->free_slots++;
        }
    }
}

static void fetch(model *m, uint32_t id)
{
    const uint64_t bytes = m->ps->pts[id].bytes;
    if (m->resident[id]) {
        lru_remove(m, id);
        return;
    }
    while (m->lru_count > 0 && m->held + bytes > m->budget) {
        const uint32_t old = m->lru[0];
        m->resident[old] = 0;
        m->held -= m->ps->pts[old].bytes + (m->decode[old] ? DECODED_BYTES : 0);
        m->decoded -= m->decode[old] ? DECODED_BYTES : 0;
        m->decode[old] = 0;
        lru_remove(m, old);
    }
    m->resident[id] = 1;
    m->held += bytes;
    if (m->budget >= m->ps->all_bytes &&                /* layer 8 */
        DECODED_BYTES <= m->budget - m->ps->all_bytes - m->decoded) {
        m->decode[id] = 1;
        m->decoded += DECODED_BYTES;
        m->held += DECODED_BYTES;
    }
    if (m->held > m->peak) m->peak = m->held;
    if (m->load_count < MAX_LOADS) m->loads[m->load_count] = id;
    m->load_count++;
}

/* The whole trace of the model with rays_in_flight slots. */
static void model_run(model *m, const policy_scene *ps, int paper, int no_proxy, uint64_t limit,
                      uint32_t in_flight)
{
    memset(m, 0, sizeof *m);
    m->ps = ps;
    m->paper = paper;
    m->budget = limit ? limit : UINT64_MAX;
    if (limit && !no_proxy) m->budget = limit > ps->proxy_bytes ? limit - ps->proxy_bytes : 0;
    m->proxies = !no_proxy && (paper || m->budget < ps->all_bytes);    /* layer 1 */
    m->free_slots = in_flight;
    refill(m);
    for (;;) {
        uint32_t id, best = NP, q[NR], n, i;
        for (id = 0; id < NP; id++)
            if (m->queued[id] > 0 && (best == NP || m->queued[id] > m->queued[best])) best = id;
        if (best == NP) break;
        fetch(m, best);
        n = m->queued[best];
        memcpy(q, m->queue[best], n * sizeof *q);
        m->queued[best] = 0;
        for (i = 0; i < n; i++) meet(m, q[i], best);
        lru_push(m, best);                              /* released */
        for (i = 0; i < n; i++)
            if (walk(m, q[i]) < 0) m->free_slots++;
        refill(m);
    }
}

/* ---- the library ---------------------------------------------------------- */

static long logging_read(int fd, void *buf, size_t size, uint64_t offset, void *user)
{
    load_log *log = user;
    uint32_t j;
    for (j = 0; j < NP; j++)
        if (log->ps->pts[j].offset == offset) {
            if (log->count < MAX_LOADS) log->ids[log->count] = j;
            log->count++;
        }
    return (long)pread(fd, buf, size, (off_t)offset);
}

static int library_run(const policy_scene *ps, int paper, int no_proxy, uint64_t limit, uint32_t in_flight,
                       load_log *log, brt_stats *stats, brt_hit *hits)
{
    brt_trace_options opt;
    brt_error err;
    memset(&opt, 0, sizeof opt);
    memset(log, 0, sizeof *log);
    log->ps = ps;
    opt.paper_scheduler = paper;
    opt.no_proxy = no_proxy;
    opt.memory_limit = limit;
    opt.rays_in_flight = in_flight;
    opt.threads = 1;            /* no read-ahead: every read is a load */
    opt.read_fn = logging_read;
    opt.read_user = log;
    if (brt_scene_trace(ps->scene, &opt, ps->rays, ps->ray_count, hits, stats, &err) == BRT_OK) return 1;
    test_fail_at(__FILE__, __LINE__, "trace: %s", err.message);
    return 0;
}

static void print_loads(const char *who, const uint32_t *ids, uint32_t n)
{
    uint32_t i;
    printf("  %s:", who);
    for (i = 0; i < n && i < 60; i++) printf(" %u", (unsigned)ids[i]);
    printf("%s\n", n > 60 ? " ..." : "");
}

/* One setting: the library's loads and counts equal the model's, and its
** hits are the model's (a sanity check of the model's geometry). */
static void compare_setting(const policy_scene *ps, int paper, int no_proxy, uint64_t budget,
                            uint32_t in_flight)
{
    static model m;
    static load_log log;
    static brt_hit hits[NR];
    const uint64_t limit = budget ? budget + (no_proxy ? 0 : ps->proxy_bytes) : 0;
    brt_stats stats;
    uint32_t i, first = 0;
    char what[160];
    snprintf(what, sizeof what, "%s scheduler%s, %g pages, %u in flight",
             paper ? "the paper's" : "batchrt's", no_proxy ? " without proxies" : "",
             (double)budget / 4096.0, (unsigned)in_flight);
    model_run(&m, ps, paper, no_proxy, limit, in_flight);
    if (!library_run(ps, paper, no_proxy, limit, in_flight, &log, &stats, hits)) return;
    for (i = 0; i < ps->ray_count; i++)
        if ((isinf(m.hit[i]) != isinf(hits[i].t)) || (!isinf(m.hit[i]) && fabs(hits[i].t - m.hit[i]) > 1e-3))
            break;
    EXPECT(i == ps->ray_count, "%s: ray %u: the library's hit t %g, the model's %g", what, (unsigned)i,
           i < ps->ray_count ? hits[i].t : 0.0, i < ps->ray_count ? m.hit[i] : 0.0);
    while (first < log.count && first < m.load_count && first < MAX_LOADS && log.ids[first] == m.loads[first])
        first++;
    if (log.count != m.load_count || first < log.count) {
        test_fail_at(__FILE__, __LINE__, "%s: %u loads, the model %u; first difference at load %u", what,
                     (unsigned)log.count, (unsigned)m.load_count, (unsigned)first);
        print_loads("library", log.ids, log.count);
        print_loads("model  ", m.loads, m.load_count);
        return;
    }
    EXPECT(stats.batch_loads == m.load_count, "%s: batch_loads %llu, loads read %u", what,
           (unsigned long long)stats.batch_loads, (unsigned)m.load_count);
    EXPECT(stats.proxy_tests == m.proxy_tests && stats.proxy_culled == m.proxy_culled,
           "%s: proxy tests %llu culled %llu, the model %llu and %llu", what,
           (unsigned long long)stats.proxy_tests, (unsigned long long)stats.proxy_culled,
           (unsigned long long)m.proxy_tests, (unsigned long long)m.proxy_culled);
    EXPECT(stats.queued_visits == m.queued_visits && stats.resident_visits == m.resident_visits,
           "%s: queued %llu resident %llu, the model %llu and %llu", what,
           (unsigned long long)stats.queued_visits, (unsigned long long)stats.resident_visits,
           (unsigned long long)m.queued_visits, (unsigned long long)m.resident_visits);
    EXPECT(stats.cache_peak_bytes == m.peak, "%s: cache peak %llu bytes, the model %llu", what,
           (unsigned long long)stats.cache_peak_bytes, (unsigned long long)m.peak);
    EXPECT(stats.decoded_bytes == m.decoded, "%s: %llu bytes decoded, the model %llu", what,
           (unsigned long long)stats.decoded_bytes, (unsigned long long)m.decoded);
}

/* The loads, evictions (through reloads) and counts of both schedulers,
** with and without proxies, at memory limits of 1 to 5 pages above the
** proxies' bytes (2.5: not a whole number of blobs), every blob and room
** for two decoded points and a byte less (two points decoded, then one),
** and none, with few and many rays in flight. */
static void test_policies_match_model(void)
{
    static policy_scene ps;
    uint64_t budgets[8] = {2 * 2048, 4 * 2048, 5 * 2048, 6 * 2048, 10 * 2048, 0, 0, 0};
    static const uint32_t in_flight[] = {3, 16, NR};
    brt_stats stats;
    load_log log;
    static brt_hit hits[NR];
    size_t p, f;
    int paper, no_proxy;
    CHECK(policy_scene_make(&ps, "policy.brs"), "could not make the policy scene (%u clear rays)",
          (unsigned)ps.ray_count);
    /* The proxies' bytes, which the limit pays for first (the paper's Fig. 3). */
    if (library_run(&ps, 1, 0, 0, NR, &log, &stats, hits)) ps.proxy_bytes = stats.proxy_bytes;
    CHECK(ps.proxy_bytes > 0, "no proxy bytes reported");
    budgets[5] = ps.all_bytes + 2 * DECODED_BYTES;     /* two points decoded */
    budgets[6] = budgets[5] - 1;                        /* one */
    for (paper = 0; paper < 2; paper++)
        for (no_proxy = 0; no_proxy < 2; no_proxy++)
            for (p = 0; p < sizeof budgets / sizeof *budgets; p++)
                for (f = 0; f < sizeof in_flight / sizeof *in_flight && !test_failed(); f++)
                    compare_setting(&ps, paper, no_proxy, budgets[p], in_flight[f]);
    policy_scene_free(&ps);
}

/* ---- the gate of a point of instances ---------------------------------- */

/* A point of instances' proxy answers only for rays whose margin (the
** rounding of their transform, growing with the origin's distance) fits
** in its dilation; a ray from farther away is admitted untested
** (proxy_admits).  Four unit squares in a row, 1 apart, instances of one
** prototype, form one point (a world triangle far off another); rays
** straight down through the squares' centres and through the gaps
** between them.  From 2 units above, each is tested once and the gap
** rays, half a unit from any square (4.5 cells of res 64), are culled:
** the count is the number of gap rays.  From 10^5 units above, none is
** culled (admitted untested; the cast from there, grown for its
** rounding, would admit them too).  Every hit equals the brute force's. */
/* Builds and opens the squares scene s at proxy resolution 64 as NAME;
** 0 (the test failed) when it cannot, s freed then. */
static int open_squares(tu_instanced *s, const char *name, brt_scene **scene)
{
    brt_scene_source source;
    brt_scene_options sopt;
    brt_error err;
    tu_instanced_source(s, &source);
    memset(&sopt, 0, sizeof sopt);
    sopt.proxy_res = 64;
    if (brt_scene_build_source(&source, &sopt, 1, tu_scratch(name), &err) != BRT_OK ||
        brt_scene_open(tu_scratch(name), scene, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s: %s", name, err.message);
        tu_instanced_free(s);
        return 0;
    }
    return 1;
}

static void test_instance_gate(void)
{
    tu_instanced s;
    brt_scene *scene = NULL;
    brt_error err;
    brt_ray rays[7];
    brt_hit hits[7];
    int k, far;
    tu_instanced_squares(&s);
    if (!open_squares(&s, "gate.brs", &scene)) return;
    for (far = 0; far < 2 && !test_failed(); far++) {
        brt_trace_options opt;
        brt_stats stats;
        for (k = 0; k < 7; k++) {   /* even k: a square's centre; odd: a gap */
            brt_ray r = {{0, 0.5f, 0}, {0, 0, -1}, 0, INFINITY};
            r.org[0] = 0.5f + (float)k;
            r.org[2] = far ? 1e5f : 3.0f;
            rays[k] = r;
        }
        memset(&opt, 0, sizeof opt);
        opt.paper_scheduler = 1;        /* proxies consulted whatever the limit */
        opt.threads = 1;
        if (brt_scene_trace(scene, &opt, rays, 7, hits, &stats, &err) != BRT_OK) {
            test_fail_at(__FILE__, __LINE__, "trace: %s", err.message);
            break;
        }
        for (k = 0; k < 7; k++) {
            brt_hit want;
            brt_hit_clear(&want);
            tu_instanced_brute(&s, &rays[k], &want);
            EXPECT(hits[k].prim == want.prim && hits[k].inst == want.inst && (k % 2 == 1) == (want.prim == BRT_NO_PRIM),
                   "%s ray %d: prim %u inst %u, brute force %u %u", far ? "far" : "near", k,
                   (unsigned)hits[k].prim, (unsigned)hits[k].inst, (unsigned)want.prim, (unsigned)want.inst);
        }
        EXPECT(stats.batching_points == 2 && stats.proxy_tests == 7 && stats.proxy_culled == (far ? 0u : 3u),
               "%s rays: %llu points, %llu proxy tests, %llu culled; expected 2, 7 and %u", far ? "far" : "near",
               (unsigned long long)stats.batching_points, (unsigned long long)stats.proxy_tests,
               (unsigned long long)stats.proxy_culled, far ? 0u : 3u);
    }
    brt_scene_close(scene);
    tu_instanced_free(&s);
}

/* README, "Memory": a point of instances is charged its table in memory
** too: per instance its frame (brt_instance_frame), three 32-bit numbers
** and one top-level node of 112 bytes, beside the page-rounded blobs.
** Rays down through the four squares load the point of instances and its
** prototype, nothing else (decoding off): the cache's peak is those two
** blobs' pages and four instances' tables, to the byte.  The blob sizes
** come from the scene file's tables (README, "The scene file": version 4,
** 104-byte batch entries, the prototype table in the fourth section). */
static void test_instance_table_charged(void)
{
    tu_instanced s;
    brt_scene_source source;
    brt_scene_options sopt;
    brt_scene *scene = NULL;
    brt_trace_options opt;
    brt_stats stats;
    brt_error err;
    brt_ray rays[4];
    brt_hit hits[4];
    unsigned char *f;
    size_t fsize;
    uint64_t want = 0, instances = 0;
    uint32_t j, points, prototypes;
    int k;
    tu_instanced_squares(&s);
    tu_instanced_source(&s, &source);
    memset(&sopt, 0, sizeof sopt);
    if (brt_scene_build_source(&source, &sopt, 1, tu_scratch("charge.brs"), &err) != BRT_OK ||
        brt_scene_open(tu_scratch("charge.brs"), &scene, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "charge.brs: %s", err.message);
        tu_instanced_free(&s);
        return;
    }
    f = tu_slurp(tu_scratch("charge.brs"), &fsize);
    if (!f || fsize < 256 || brt_get_le32(f + 8) != 4) {
        EXPECT(0, "charge.brs is not a scene file of version 4");
        goto done;
    }
    points = brt_get_le32(f + 32);
    prototypes = brt_get_le32(f + 44);
    for (j = 0; j < points; j++) {
        const unsigned char *e = f + brt_get_le64(f + 56) + 104u * j;
        if (brt_get_le32(e + 80) == 0) continue;          /* the world's point: not reached */
        instances += brt_get_le32(e + 80);
        want += (brt_get_le64(e + 32) + 4095) / 4096 * 4096;
        /* its entry's instanced triangles: each instance's prototype's two */
        EXPECT(brt_get_le64(e + 88) == 2u * brt_get_le32(e + 80), "point %u: %llu instanced triangles, want %u",
               (unsigned)j, (unsigned long long)brt_get_le64(e + 88), 2u * brt_get_le32(e + 80));
    }
    for (j = 0; j < prototypes; j++)
        want += (brt_get_le64(f + brt_get_le64(f + 128) + 56u * j + 8) + 4095) / 4096 * 4096;
    want += instances * (sizeof(brt_instance_frame) + 3 * 4 + 112);
    for (k = 0; k < 4; k++) {
        brt_ray r = {{0, 0.5f, 3}, {0, 0, -1}, 0, INFINITY};
        r.org[0] = 0.5f + 2.0f * (float)k;
        rays[k] = r;
    }
    memset(&opt, 0, sizeof opt);
    opt.threads = 1;
    opt.no_decode = 1;
    if (brt_scene_trace(scene, &opt, rays, 4, hits, &stats, &err) != BRT_OK) {
        EXPECT(0, "trace: %s", err.message);
        goto done;
    }
    EXPECT(instances == 4 && prototypes == 1 && stats.batch_loads == 1 && stats.prototype_loads == 1,
           "%llu instances, %u prototypes, %llu loads, %llu prototype loads (want 4, 1, 1, 1)",
           (unsigned long long)instances, (unsigned)prototypes, (unsigned long long)stats.batch_loads,
           (unsigned long long)stats.prototype_loads);
    EXPECT(stats.cache_peak_bytes == want, "cache peak %llu bytes, want %llu: two blobs' pages and 4 instances' tables",
           (unsigned long long)stats.cache_peak_bytes, (unsigned long long)want);
done:
    free(f);
    brt_scene_close(scene);
    tu_instanced_free(&s);
}

/* The scene's margin (README, "Instances": boxes of instances grown by
** 64 FLT_EPSILON k (|o - c| + R)) needs R to reach every instance's
** translation from the centre c, on both sides: the header's reach (byte
** 160, with c at 176) is at least the farthest translation's distance on
** any axis.  The four squares with the world triangle moved to x = -100:
** the centre lies left of the instances, so the largest translation is the
** farthest. */
static void test_margin_reaches_every_instance(void)
{
    tu_instanced s;
    brt_scene_source source;
    brt_scene_options sopt;
    brt_error err;
    unsigned char *f = NULL;
    size_t fsize = 0;
    uint32_t k;
    double far = 0;
    float reach = 0, centre[3];
    int a;
    tu_instanced_squares(&s);
    for (k = 0; k < s.world.vcount; k++) s.world.pos[3 * k] -= 200;      /* x 100 -> -100 */
    tu_instanced_source(&s, &source);
    memset(&sopt, 0, sizeof sopt);
    if (brt_scene_build_source(&source, &sopt, 1, tu_scratch("margin.brs"), &err) != BRT_OK) {
        EXPECT(0, "margin.brs: %s", err.message);
        tu_instanced_free(&s);
        return;
    }
    f = tu_slurp(tu_scratch("margin.brs"), &fsize);
    if (f && fsize >= 256 && brt_get_le32(f + 8) == 4) {
        reach = le_f32(f + 160);
        for (a = 0; a < 3; a++) centre[a] = le_f32(f + 176 + 4 * a);
        for (k = 0; k < s.instance_count; k++)
            for (a = 0; a < 3; a++) far = fmax(far, fabs((double)s.instances[k].xform[4 * a + 3] - centre[a]));
        EXPECT(far > 50 && reach >= far, "reach %g, but an instance's translation lies %g from the centre", reach, far);
    } else
        EXPECT(0, "margin.brs is not a scene file of version 4");
    free(f);
    tu_instanced_free(&s);
}

/* The gate above, with the whole scene moved 10^4 along x: a point's
** margin is taken about the centre of its own instances (not the origin),
** so near rays keep their small margins and the gap rays are culled as
** before; a margin about the origin would reach 10^4 and admit them all
** untested. */
static void test_instance_gate_far_from_origin(void)
{
    const float shift = 1e4f;
    tu_instanced s;
    brt_scene *scene = NULL;
    brt_trace_options opt;
    brt_stats stats;
    brt_error err;
    brt_ray rays[7];
    brt_hit hits[7];
    uint32_t k;
    tu_instanced_squares(&s);
    for (k = 0; k < s.world.vcount; k++) s.world.pos[3 * k] += shift;
    for (k = 0; k < s.instance_count; k++) s.instances[k].xform[3] += shift;
    if (!open_squares(&s, "gate-far.brs", &scene)) return;
    for (k = 0; k < 7; k++) {
        brt_ray r = {{0, 0.5f, 3.0f}, {0, 0, -1}, 0, INFINITY};
        r.org[0] = shift + 0.5f + (float)k;
        rays[k] = r;
    }
    memset(&opt, 0, sizeof opt);
    opt.paper_scheduler = 1;
    opt.threads = 1;
    if (brt_scene_trace(scene, &opt, rays, 7, hits, &stats, &err) == BRT_OK) {
        for (k = 0; k < 7; k++) {
            brt_hit want;
            brt_hit_clear(&want);
            tu_instanced_brute(&s, &rays[k], &want);
            EXPECT(hits[k].prim == want.prim && hits[k].inst == want.inst, "ray %u: prim %u inst %u, brute force %u %u",
                   (unsigned)k, (unsigned)hits[k].prim, (unsigned)hits[k].inst, (unsigned)want.prim,
                   (unsigned)want.inst);
        }
        EXPECT(stats.proxy_tests == 7 && stats.proxy_culled == 3,
               "moved 10^4: %llu proxy tests, %llu culled; expected 7 and 3 (the gap rays)",
               (unsigned long long)stats.proxy_tests, (unsigned long long)stats.proxy_culled);
    } else
        EXPECT(0, "trace: %s", err.message);
    brt_scene_close(scene);
    tu_instanced_free(&s);
}

/* ---- the proxy test's segment ends at the closest hit so far ------------ */

typedef struct bytes_log {      /* every read: its offset and size */
    uint64_t offsets[64], bytes;
    uint32_t count;
} bytes_log;

static long bytes_read(int fd, void *buf, size_t size, uint64_t offset, void *user)
{
    bytes_log *log = user;
    if (log->count < 64) log->offsets[log->count] = offset;
    log->count++;
    log->bytes += size;
    return (long)pread(fd, buf, size, (off_t)offset);
}

/* README, "The scheduler": a ray's proxy is asked about [tnear, closest
** hit so far] ("A ray is first cast against a small in-memory voxel proxy
** ... only rays that hit the proxy cause a disk load"; walk_on, proxy_test).
** Hits cannot show a proxy cast over the whole [tnear, tfar]: it only
** loads more.  Two batching points of one triangle each, rays along +x
** from x = -1 near the axis y = z = 0:
**   A, the plane x = 1 + y/2 (box x in [0.5, 1.5]), crossed at x ~ 1;
**   B, a triangle from a corner at x = 0.8, (y, z) = (2, 2), to an edge at
**      x = 3.2, crossed at x ~ 2.84.
** Every ray enters A first (t ~ 1.5), is queued there and hits it (t ~ 2);
** it walks on into B's box (entered at t ~ 1.8, before that hit), where
** B's triangle lies at least ~1.7 (9 cells of 16^3 over a box of 3) from
** the ray up to the hit: the proxy misses over [tnear, t_A] and would hit
** over [tnear, inf].  Closed counts for N rays, both schedulers, a limit
** one byte under every blob (layer 1 keeps the proxies on): one load,
** A's blob's bytes read, 2N proxy tests, N culled, N visits, all queued. */
static void test_proxy_segment_to_closest_hit(void)
{
    enum { N = 25 };
    static const float tri[2][3][3] = {
        {{0.5f, -1, -1}, {0.5f, -1, 1}, {1.5f, 1, 0}},
        {{0.8f, 2, 2}, {3.2f, -1, 0.3f}, {3.2f, 0.3f, -1}}};
    tu_scene s;
    brt_scene *scene;
    brt_ray rays[N];
    brt_hit hits[N];
    brt_stats unlimited, st;
    brt_trace_options opt;
    brt_error err;
    bytes_log log;
    uint64_t a_offset = 0, a_size = 0, all_blobs = 0;
    unsigned char *f;
    size_t fsize;
    uint32_t i, j;
    int paper;
    memset(&s, 0, sizeof s);
    for (i = 0; i < 2; i++) {
        uint32_t v[3];
        for (j = 0; j < 3; j++) v[j] = tu_add_vertex(&s, tri[i][j][0], tri[i][j][1], tri[i][j][2]);
        tu_add_triangle(&s, v[0], v[1], v[2]);
    }
    scene = tu_build_scene(&s, 1, 16, 1, tu_scratch("segment.brs"));
    CHECK(scene, "no scene");
    f = tu_slurp(tu_scratch("segment.brs"), &fsize);
    CHECK(f && brt_get_le32(f + 32) == 2, "want two batching points of one triangle each");
    for (j = 0; j < 2; j++) {          /* the point table: box lo x at 0, blob offset 24, size 32 */
        const unsigned char *e = f + brt_get_le64(f + 56) + 80u * j;
        all_blobs += (brt_get_le64(e + 32) + 4095) / 4096 * 4096;
        if (le_f32(e) < 0.6f) {       /* read whole pages, as the cache holds them */
            a_offset = brt_get_le64(e + 24);
            a_size = (brt_get_le64(e + 32) + 4095) / 4096 * 4096;
        }
    }
    free(f);
    CHECK(a_size > 0, "no batching point with A's box");
    for (i = 0; i < N; i++) {
        brt_hit want;
        rays[i].org[0] = -1;
        rays[i].org[1] = 0.02f * (float)(i % 5) - 0.04f;
        rays[i].org[2] = 0.02f * (float)(i / 5) - 0.04f;
        rays[i].dir[0] = 1;
        rays[i].dir[1] = rays[i].dir[2] = 0;
        rays[i].tnear = 0;
        rays[i].tfar = INFINITY;
        brt_hit_clear(&want);
        tu_brute_force(&s, NULL, &rays[i], &want);
        CHECK(want.prim == 0 && want.t > 1.9f && want.t < 2.1f, "ray %u: brute force says prim %u t %g",
              (unsigned)i, (unsigned)want.prim, want.t);
    }
    memset(&opt, 0, sizeof opt);
    opt.threads = 1;
    CHECK(brt_scene_trace(scene, &opt, rays, N, hits, &unlimited, &err) == BRT_OK, "%s", err.message);
    /* paper 0 and 1: batchrt's and the paper's scheduler; 2: the paper's
    ** with exact proxies (layer 5: the triangles answer the proxy test, up
    ** to the closest hit too). */
    for (paper = 0; paper < 3; paper++) {
        memset(&log, 0, sizeof log);
        opt.paper_scheduler = paper > 0;
        opt.exact_proxies = paper == 2;
        opt.memory_limit = unlimited.proxy_bytes + all_blobs - 1;
        opt.read_fn = bytes_read;
        opt.read_user = &log;
        CHECK(brt_scene_trace(scene, &opt, rays, N, hits, &st, &err) == BRT_OK, "%s", err.message);
        for (i = 0; i < N; i++)
            EXPECT(hits[i].prim == 0 && hits[i].t > 1.9f, "%s: ray %u: prim %u t %g",
                   paper == 2 ? "exact proxies" : paper ? "paper's" : "batchrt's", (unsigned)i, (unsigned)hits[i].prim, hits[i].t);
        /* (exact proxies read triangles for their answers too: analysis, not loads) */
        EXPECT(paper == 2 || (log.count == 1 && log.offsets[0] == a_offset && log.bytes == a_size),
               "%s scheduler: %u reads, %llu bytes (want A's blob alone: one read of %llu bytes); B's proxy "
               "was cast beyond the closest hit", paper == 2 ? "exact proxies" : paper ? "paper's" : "batchrt's", (unsigned)log.count,
               (unsigned long long)log.bytes, (unsigned long long)a_size);
        EXPECT(st.batch_loads == 1 && st.disk_bytes_read == (paper == 2 ? a_size : log.bytes) && st.proxy_tests == 2 * N &&
               st.proxy_culled == N && st.visits == N && st.queued_visits == N && st.resident_visits == 0,
               "%s scheduler: loads %llu (want 1), disk bytes %llu (read %llu), proxy tests %llu (want %d), "
               "culled %llu (want %d), visits %llu = %llu queued + %llu resident (want %d, all queued)",
               paper == 2 ? "exact proxies" : paper ? "paper's" : "batchrt's", (unsigned long long)st.batch_loads,
               (unsigned long long)st.disk_bytes_read, (unsigned long long)log.bytes,
               (unsigned long long)st.proxy_tests, 2 * N, (unsigned long long)st.proxy_culled, N,
               (unsigned long long)st.visits, (unsigned long long)st.queued_visits,
               (unsigned long long)st.resident_visits, N);
    }
    /* The budget exactly A's pages: no load is oversized; a byte less, A's
    ** is (README: "a blob larger than the whole budget, held alone").  And
    ** the statistics file says the closed counts, field by field. */
    opt.paper_scheduler = 0;
    opt.exact_proxies = 0;
    opt.read_fn = NULL;
    for (i = 0; i < 2; i++) {
        static const char *const fields[] = {"rays", "batching_points", "batch_loads", "disk_bytes_read",
                                             "cache_peak_bytes", "memory_limit", "proxy_tests", "proxy_culled",
                                             "visits", "queued_visits", "resident_visits", "oversized_loads",
                                             "occlusion_rays", "occlusion_batch_loads", "prototype_loads"};
        double want[15];
        size_t k;
        opt.memory_limit = unlimited.proxy_bytes + a_size - i;
        CHECK(brt_scene_trace(scene, &opt, rays, N, hits, &st, &err) == BRT_OK, "%s", err.message);
        CHECK(brt_stats_write_json(tu_scratch("segment.json"), &st, &err) == BRT_OK, "%s", err.message);
        want[0] = N; want[1] = 2; want[2] = 1; want[3] = (double)a_size; want[4] = (double)a_size;
        want[5] = (double)opt.memory_limit; want[6] = 2 * N; want[7] = N; want[8] = N; want[9] = N;
        want[10] = 0; want[11] = i; want[12] = 0; want[13] = 0; want[14] = 0;
        for (k = 0; k < 15; k++)
            EXPECT(tu_json_file_number(tu_scratch("segment.json"), fields[k]) == want[k],
                   "budget %s A's pages: \"%s\" is %.0f, want %.0f", i ? "a byte under" : "exactly",
                   fields[k], tu_json_file_number(tu_scratch("segment.json"), fields[k]), want[k]);
    }
    brt_scene_close(scene);
    tu_scene_free(&s);
}

void suite_policy(void)
{
    test_run("policy: loads and counts equal the model's", test_policies_match_model);
    test_run("policy: the gate of a point of instances", test_instance_gate);
    test_run("policy: a point of instances is charged its table", test_instance_table_charged);
    test_run("policy: the gate of a point of instances far from the origin", test_instance_gate_far_from_origin);
    test_run("policy: the margin reaches every instance's translation", test_margin_reaches_every_instance);
    test_run("policy: the proxy segment ends at the closest hit", test_proxy_segment_to_closest_hit);
}
