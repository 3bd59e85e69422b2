/*
** tests/test_layers.c -- the rules of the scheduler's layers and of its
** ray-source contract that no hit can show (batchrt.c, "ray queues and
** the scheduler").
**
** Every layer keeps the hits, so the byte-equality tests cannot see a
** layer that switches on at the wrong moment.  These tests pin each rule
** at its boundary instead, against numbers the library reports for
** another reason (the cache's peak bytes, the proxies' bytes).  One test
** holds where the layers are read: batchrt.c's Part II, a section each,
** in the order of the README's table.
*/
#include "test.h"
#include "util.h"

#include <signal.h>
#include <stdlib.h>
#include <string.h>

static brt_scene *layers_scene(tu_scene *s, const char *name)
{
    uint64_t st = test_seed() + 41;
    memset(s, 0, sizeof *s);
    tu_random_soup(s, &st, 3000, 0.04f);
    return tu_build_scene(s, 200, 16, 0, tu_scratch(name));
}

static brt_ray *layers_rays(const tu_scene *s, size_t count)
{
    brt_ray *rays = malloc(count * sizeof *rays);
    float lo[3], hi[3];
    uint64_t st = test_seed() + 42;
    size_t i;
    tu_scene_bounds(s, lo, hi);
    for (i = 0; rays && i < count; i++) tu_make_ray(s, lo, hi, TU_RANDOM, &st, &rays[i]);
    return rays;
}

/* Layer 1: the default scheduler leaves the proxies alone exactly when
** the budget after the proxies holds every blob (what the cache holds at
** its peak when nothing is evicted). */
static void test_layer2_boundary(void)
{
    enum { COUNT = 4000 };
    tu_scene s;
    brt_scene *scene = layers_scene(&s, "layer2.brs");
    brt_ray *rays = layers_rays(&s, COUNT);
    brt_hit *hits = malloc(COUNT * sizeof *hits);
    brt_trace_options opt;
    brt_stats all, at, below;
    brt_error err;
    CHECK(scene && rays && hits, "set-up failed");
    memset(&opt, 0, sizeof opt);
    opt.threads = 1;
    CHECK(brt_scene_trace(scene, &opt, rays, COUNT, hits, &all, &err) == BRT_OK, "%s", err.message);
    CHECK(all.batch_loads == all.batching_points, "unlimited: %llu loads of %llu points; the rays must "
          "reach every point once", (unsigned long long)all.batch_loads,
          (unsigned long long)all.batching_points);
    opt.memory_limit = all.cache_peak_bytes - all.decoded_bytes + all.proxy_bytes;
    CHECK(brt_scene_trace(scene, &opt, rays, COUNT, hits, &at, &err) == BRT_OK, "%s", err.message);
    opt.memory_limit--;
    CHECK(brt_scene_trace(scene, &opt, rays, COUNT, hits, &below, &err) == BRT_OK, "%s", err.message);
    EXPECT(at.proxy_tests == 0, "a budget holding every blob still consulted the proxies (%llu tests)",
           (unsigned long long)at.proxy_tests);
    EXPECT(below.proxy_tests > 0, "a byte less and the proxies were not consulted");
    brt_scene_close(scene);
    tu_scene_free(&s);
    free(rays);
    free(hits);
}

/* Layer 8: without a limit every batching point is decoded (the peak is
** every blob and every layout); with no_decode none is, and the hits and
** loads are the same; with a budget of every blob and nothing more, none
** is either (a decoded point would leave a blob no room). */
static void test_layer9_decoded_points(void)
{
    enum { COUNT = 4000 };
    tu_scene s;
    brt_scene *scene = layers_scene(&s, "layer9.brs");
    brt_ray *rays = layers_rays(&s, COUNT);
    brt_hit *hits = malloc(COUNT * sizeof *hits), *quantized = malloc(COUNT * sizeof *quantized);
    brt_trace_options opt;
    brt_stats decoded, plain, tight, half;
    brt_error err;
    uint64_t room;
    CHECK(scene && rays && hits && quantized, "set-up failed");
    memset(&opt, 0, sizeof opt);
    opt.threads = 1;
    CHECK(brt_scene_trace(scene, &opt, rays, COUNT, hits, &decoded, &err) == BRT_OK, "%s", err.message);
    opt.no_decode = 1;
    CHECK(brt_scene_trace(scene, &opt, rays, COUNT, quantized, &plain, &err) == BRT_OK, "%s", err.message);
    opt.no_decode = 0;
    opt.memory_limit = plain.cache_peak_bytes + plain.proxy_bytes;
    CHECK(brt_scene_trace(scene, &opt, rays, COUNT, hits, &tight, &err) == BRT_OK, "%s", err.message);
    EXPECT(decoded.decoded_bytes > 0 &&
           decoded.cache_peak_bytes == plain.cache_peak_bytes + decoded.decoded_bytes,
           "unlimited: %llu bytes decoded beside %llu of blobs, peak %llu",
           (unsigned long long)decoded.decoded_bytes, (unsigned long long)plain.cache_peak_bytes,
           (unsigned long long)decoded.cache_peak_bytes);
    EXPECT(plain.decoded_bytes == 0 && tight.decoded_bytes == 0,
           "decoded %llu bytes with no_decode, %llu with room for the blobs only",
           (unsigned long long)plain.decoded_bytes, (unsigned long long)tight.decoded_bytes);
    EXPECT(memcmp(hits, quantized, COUNT * sizeof *hits) == 0 &&
           decoded.batch_loads == plain.batch_loads && tight.batch_loads == plain.batch_loads,
           "decoded points changed the hits or the loads (%llu, %llu, %llu)",
           (unsigned long long)decoded.batch_loads, (unsigned long long)plain.batch_loads,
           (unsigned long long)tight.batch_loads);
    /* Room for half the decoded bytes beside every blob: the points share
    ** that room (each is decoded only into what the points decoded before
    ** it left), so the decoded bytes and the peak stay within the limit
    ** and no blob is evicted for a decoded one. */
    room = decoded.decoded_bytes / 2;
    opt.memory_limit = plain.cache_peak_bytes + plain.proxy_bytes + room;
    CHECK(brt_scene_trace(scene, &opt, rays, COUNT, hits, &half, &err) == BRT_OK, "%s", err.message);
    EXPECT(half.decoded_bytes > 0 && half.decoded_bytes <= room &&
               half.cache_peak_bytes + half.proxy_bytes <= opt.memory_limit && half.batch_loads == plain.batch_loads,
           "room for %llu decoded bytes: %llu decoded, peak %llu + proxies %llu over the limit %llu?, loads %llu "
           "(want %llu)", (unsigned long long)room, (unsigned long long)half.decoded_bytes,
           (unsigned long long)half.cache_peak_bytes, (unsigned long long)half.proxy_bytes,
           (unsigned long long)opt.memory_limit, (unsigned long long)half.batch_loads,
           (unsigned long long)plain.batch_loads);
    EXPECT(memcmp(hits, quantized, COUNT * sizeof *hits) == 0, "room for half the decoded bytes changed the hits");
    brt_scene_close(scene);
    tu_scene_free(&s);
    free(rays);
    free(hits);
    free(quantized);
}

/* README, "Memory" and "Statistics": a batched run holds its memory limit
** (geometry cache and proxies); cache_peak_bytes <= memory_limit, a blob
** larger than the whole budget is the only oversized load.  At the byte:
** with the limit exactly every blob (page-rounded, as the cache holds
** them: the unlimited run's peak, no decode) plus the proxies, nothing is
** evicted: each point loaded once, the peak every blob, the bytes read
** the unlimited run's, no oversized load.  One byte under, the peak stays
** within the budget and no blob is oversized (each is far smaller).  The
** reference is the unlimited run, whose loads equal the points (checked),
** so its peak is the sum of every blob. */
static void test_cache_at_the_limit(void)
{
    enum { COUNT = 4000 };
    tu_scene s;
    brt_scene *scene = layers_scene(&s, "atlimit.brs");
    brt_ray *rays = layers_rays(&s, COUNT);
    brt_hit *hits = malloc(COUNT * sizeof *hits);
    brt_trace_options opt;
    brt_stats all, at, below;
    brt_error err;
    CHECK(scene && rays && hits, "set-up failed");
    memset(&opt, 0, sizeof opt);
    opt.threads = 1;
    opt.no_decode = 1;
    CHECK(brt_scene_trace(scene, &opt, rays, COUNT, hits, &all, &err) == BRT_OK, "%s", err.message);
    CHECK(all.batch_loads == all.batching_points && all.oversized_loads == 0 && all.memory_limit == 0,
          "unlimited: %llu loads of %llu points, %llu oversized", (unsigned long long)all.batch_loads,
          (unsigned long long)all.batching_points, (unsigned long long)all.oversized_loads);
    opt.memory_limit = all.cache_peak_bytes + all.proxy_bytes;
    CHECK(brt_scene_trace(scene, &opt, rays, COUNT, hits, &at, &err) == BRT_OK, "%s", err.message);
    EXPECT(at.batch_loads == at.batching_points && at.cache_peak_bytes == all.cache_peak_bytes &&
           at.disk_bytes_read == all.disk_bytes_read && at.oversized_loads == 0 &&
           at.memory_limit == opt.memory_limit && at.cache_peak_bytes + at.proxy_bytes <= at.memory_limit,
           "at the limit %llu: %llu loads of %llu points, peak %llu (every blob: %llu), %llu bytes read "
           "(unlimited: %llu), %llu oversized, limit reported %llu", (unsigned long long)opt.memory_limit,
           (unsigned long long)at.batch_loads, (unsigned long long)at.batching_points,
           (unsigned long long)at.cache_peak_bytes, (unsigned long long)all.cache_peak_bytes,
           (unsigned long long)at.disk_bytes_read, (unsigned long long)all.disk_bytes_read,
           (unsigned long long)at.oversized_loads, (unsigned long long)at.memory_limit);
    /* README, Statistics: visits = queued_visits + resident_visits (this
    ** limit holds every blob, so layer 4 intersects rays at once too). */
    EXPECT(at.resident_visits > 0 && at.visits == at.queued_visits + at.resident_visits,
           "visits %llu, queued %llu, resident %llu", (unsigned long long)at.visits,
           (unsigned long long)at.queued_visits, (unsigned long long)at.resident_visits);
    opt.memory_limit--;
    CHECK(brt_scene_trace(scene, &opt, rays, COUNT, hits, &below, &err) == BRT_OK, "%s", err.message);
    EXPECT(below.cache_peak_bytes + below.proxy_bytes <= below.memory_limit && below.oversized_loads == 0,
           "a byte under: peak %llu + proxies %llu over the limit %llu, or %llu oversized",
           (unsigned long long)below.cache_peak_bytes, (unsigned long long)below.proxy_bytes,
           (unsigned long long)below.memory_limit, (unsigned long long)below.oversized_loads);
    brt_scene_close(scene);
    tu_scene_free(&s);
    free(rays);
    free(hits);
}

/* A ray source over an array that counts its finished rays and records
** the room of its first call (the rays in flight); a greedy one claims
** more rays than it was given room for. */
typedef struct test_source {
    const brt_ray *rays;
    size_t count, next, finished, first_room;
    int greedy;
} test_source;

static size_t test_next(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    test_source *g = user;
    size_t n = g->count - g->next < max ? g->count - g->next : max, i;
    if (g->first_room == 0) g->first_room = max;
    for (i = 0; i < n; i++) {
        rays[i] = g->rays[g->next];
        tags[i] = g->next++;
    }
    return g->greedy && n == max && n > 0 ? n + 7 : n;   /* the lie, only when full */
}

static void test_finished(void *user, const brt_ray *ray, const brt_hit *hit, const float normal[3],
                          uint32_t visits, uint64_t tag)
{
    (void)ray; (void)hit; (void)normal; (void)visits; (void)tag;
    ((test_source *)user)->finished++;
}

static brt_ray_source test_source_over(test_source *g, const brt_ray *rays, size_t count, int greedy)
{
    brt_ray_source source;
    memset(g, 0, sizeof *g);
    g->rays = rays;
    g->count = count;
    g->greedy = greedy;
    source.next_rays = test_next;
    source.finished = test_finished;
    source.user = g;
    return source;
}

/* The source contract: more rays than room is an error of the trace, not
** a slot count that wraps around. */
static void test_source_contract(void)
{
    enum { COUNT = 300 };
    tu_scene s;
    brt_scene *scene = layers_scene(&s, "source.brs");
    brt_ray *rays = layers_rays(&s, COUNT);
    test_source g;
    brt_ray_source source;
    brt_trace_options opt;
    brt_error err;
    brt_result r;
    CHECK(scene && rays, "set-up failed");
    source = test_source_over(&g, rays, COUNT, 1);
    memset(&opt, 0, sizeof opt);
    opt.rays_in_flight = 64;
    err.message[0] = 0;
    r = brt_scene_trace_stream(scene, &opt, &source, NULL, &err);
    EXPECT(r == BRT_EARG && strstr(err.message, "next_rays"), "a source over its room: result %d, '%s'",
           (int)r, err.message);
    EXPECT(g.finished == 0, "%lu rays finished from a source that broke the contract",
           (unsigned long)g.finished);
    brt_scene_close(scene);
    tu_scene_free(&s);
    free(rays);
}

/* The rays in flight a stream gets at a budget (0: none), by default. */
static size_t default_room(brt_scene *scene, const brt_ray *rays, size_t count, uint64_t limit)
{
    test_source g;
    const brt_ray_source source = test_source_over(&g, rays, count, 0);
    brt_trace_options opt;
    brt_stats stats;
    brt_error err;
    memset(&opt, 0, sizeof opt);
    opt.memory_limit = limit;
    opt.threads = 1;
    if (brt_scene_trace_stream(scene, &opt, &source, &stats, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s", err.message);
        return 0;
    }
    return g.first_room;
}

/* Layer 2: by default 4096 rays in flight exactly when the budget after
** the proxies holds every blob, 1 << 20 otherwise. */
static void test_layer10_rays_in_flight(void)
{
    enum { COUNT = 5000 };
    tu_scene s;
    brt_scene *scene = layers_scene(&s, "layer10.brs");
    brt_ray *rays = layers_rays(&s, COUNT);
    brt_hit *hits = malloc(COUNT * sizeof *hits);
    brt_trace_options opt;
    brt_stats all;
    brt_error err;
    size_t in_core, at, below;
    CHECK(scene && rays && hits, "set-up failed");
    memset(&opt, 0, sizeof opt);
    opt.no_decode = 1;
    CHECK(brt_scene_trace(scene, &opt, rays, COUNT, hits, &all, &err) == BRT_OK, "%s", err.message);
    in_core = default_room(scene, rays, COUNT, 0);
    at = default_room(scene, rays, COUNT, all.cache_peak_bytes + all.proxy_bytes);
    below = default_room(scene, rays, COUNT, all.cache_peak_bytes + all.proxy_bytes - 1);
    EXPECT(in_core == 4096 && at == 4096 && below == (size_t)1 << 20,
           "rays in flight %lu without a limit, %lu with room for every blob, %lu a byte less",
           (unsigned long)in_core, (unsigned long)at, (unsigned long)below);
    brt_scene_close(scene);
    tu_scene_free(&s);
    free(rays);
    free(hits);
}

/* brt_trace_options.interrupt: a flag already set stops the trace before
** its first batch, with BRT_EINTR and rays left unfinished. */
static void test_interrupt_between_batches(void)
{
    enum { COUNT = 2000 };
    tu_scene s;
    brt_scene *scene = layers_scene(&s, "interrupt.brs");
    brt_ray *rays = layers_rays(&s, COUNT);
    brt_hit *hits = malloc(COUNT * sizeof *hits);
    volatile sig_atomic_t flag = 1;
    brt_trace_options opt;
    brt_stats stats;
    brt_error err;
    brt_result r;
    CHECK(scene && rays && hits, "set-up failed");
    memset(&opt, 0, sizeof opt);
    opt.threads = 1;
    opt.paper_scheduler = 1;      /* every ray reaching a point is queued there */
    opt.interrupt = &flag;
    err.message[0] = 0;
    r = brt_scene_trace(scene, &opt, rays, COUNT, hits, &stats, &err);
    EXPECT(r == BRT_EINTR && strstr(err.message, "interrupted"), "an interrupted trace: result %d, '%s'",
           (int)r, err.message);
    EXPECT(stats.batch_loads == 0, "%llu loads after the interrupt", (unsigned long long)stats.batch_loads);
    flag = 0;
    EXPECT(brt_scene_trace(scene, &opt, rays, COUNT, hits, &stats, &err) == BRT_OK && stats.batch_loads > 0,
           "the same trace, not interrupted: %s", err.message);
    brt_scene_close(scene);
    tu_scene_free(&s);
    free(rays);
    free(hits);
}

/* ---- batchrt.c's layout: one section a layer, as the README numbers them ---- */

#define LAYERS 12

/* The line number of p in text. */
static int line_at(const char *text, const char *p)
{
    int line = 1;
    for (; text < p; text++) line += *text == '\n';
    return line;
}

/* The first line of text, from p on, that starts with prefix; or NULL. */
static const char *line_starting(const char *p, const char *prefix)
{
    size_t n = strlen(prefix);
    for (; p && *p; p = strchr(p, '\n') ? strchr(p, '\n') + 1 : NULL)
        if (strncmp(p, prefix, n) == 0) return p;
    return NULL;
}

static int ident_char(char c)
{
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_';
}

/* Where function name is DEFINED in text: the start of the line at column
** 0 that names it before a '(' and whose declaration then reaches a '{'
** before a ';' (a prototype reaches the ';'); NULL when nowhere. */
static const char *definition_of(const char *text, const char *name)
{
    size_t n = strlen(name);
    const char *line, *end, *q;
    for (line = text; *line; line = *end ? end + 1 : end) {
        end = strchr(line, '\n');
        if (!end) end = line + strlen(line);
        if (!ident_char(*line)) continue;   /* indented code, comments, #define, '}' */
        for (q = line; q + n < end; q++)
            if (strncmp(q, name, n) == 0 && q[n] == '(' && q > line && !ident_char(q[-1])) {
                const char *stop = strpbrk(q, ";{");
                if (stop && *stop == '{') return line;
            }
    }
    return NULL;
}

/* The README's table of layers ("The scheduler, and where batchrt departs
** from the paper"): row k's number must be k; fn[k] gets the first code
** span of the row (malloc'd).  Returns the rows read. */
static int readme_layers(const char *readme, char *fn[LAYERS + 1])
{
    const char *row = line_starting(readme, "| layer | what |");
    int rows = 0;
    for (row = row ? strchr(row, '\n') : NULL; row && row[1] == '|'; row = strchr(row + 1, '\n')) {
        const char *span, *close;
        long k;
        if (strncmp(row + 1, "|---", 4) == 0) continue;
        k = strtol(row + 3, NULL, 10);
        span = strchr(row + 1, '`');
        close = span ? strchr(span + 1, '`') : NULL;
        if (k != rows + 1 || k > LAYERS || !close || close > strchr(row + 1, '\n')) return rows;
        fn[k] = malloc((size_t)(close - span));
        if (!fn[k]) return rows;
        memcpy(fn[k], span + 1, (size_t)(close - span - 1));
        fn[k][close - span - 1] = 0;
        rows++;
    }
    return rows;
}

/* batchrt.c reads as the README numbers the layers: after its PART II
** marker one section a layer, headed "---- layer N: ..." for N = 1 to LAYERS
** in that order, each the only heading with its number, and each layer's
** function (the first code span of its row in the README's table)
** defined in its own section, between its heading and the next heading
** or part banner. */
static void test_layer_sections(void)
{
    char *readme = (char *)tu_slurp("README.md", NULL), *code = (char *)tu_slurp("batchrt.c", NULL);
    char *fn[LAYERS + 1] = {0};
    const char *part2, *heading[LAYERS + 2] = {0}, *h;
    int count[LAYERS + 1] = {0}, k, rows;
    CHECK(readme && code, "cannot read README.md and batchrt.c (run from the repository's top)");
    rows = readme_layers(readme, fn);
    EXPECT(rows == LAYERS, "README.md: the table of layers has %d rows numbered 1, 2, ... with a "
           "function each, not %d", rows, LAYERS);
    part2 = line_starting(code, "/* PART II -- ");
    EXPECT(part2, "batchrt.c: no line '/* PART II -- ...': the layers' part is gone");
    for (h = line_starting(code, "/* ---- layer "); h; h = line_starting(h + 1, "/* ---- layer ")) {
        char *after;
        long n = strtol(h + strlen("/* ---- layer "), &after, 10);
        if (n < 1 || n > LAYERS || *after != ':') {
            test_fail_at(__FILE__, __LINE__, "batchrt.c:%d: a layer heading without a number 1-%d and ':'",
                         line_at(code, h), LAYERS);
            continue;
        }
        if (part2 && h < part2)
            test_fail_at(__FILE__, __LINE__, "batchrt.c:%d: layer %ld's heading comes before PART II",
                         line_at(code, h), n);
        if (count[n]++ == 0) heading[n] = h;
        else
            test_fail_at(__FILE__, __LINE__, "batchrt.c:%d: layer %ld has a second heading (the first at "
                         "line %d)", line_at(code, h), n, line_at(code, heading[n]));
    }
    for (k = 1; k <= LAYERS; k++) {
        const char *next, *banner, *def;
        if (!heading[k]) {
            test_fail_at(__FILE__, __LINE__, "batchrt.c: no heading '/* ---- layer %d: ...'", k);
            continue;
        }
        if (k > 1 && heading[k - 1] && heading[k] < heading[k - 1])
            test_fail_at(__FILE__, __LINE__, "batchrt.c:%d: layer %d's heading comes before layer %d's "
                         "(line %d)", line_at(code, heading[k]), k, k - 1, line_at(code, heading[k - 1]));
        if (k > rows) continue;
        /* The section: to the next heading of any kind, or the next part's banner. */
        next = line_starting(heading[k] + 1, "/* ---- ");
        banner = line_starting(heading[k] + 1, "/* ####");
        if (!next || (banner && banner < next)) next = banner;
        if (!next) next = code + strlen(code);
        def = definition_of(code, fn[k]);
        if (!def)
            test_fail_at(__FILE__, __LINE__, "batchrt.c: %s (layer %d in the README's table) is defined "
                         "nowhere", fn[k], k);
        else if (def < heading[k] || def >= next)
            test_fail_at(__FILE__, __LINE__, "batchrt.c:%d: %s (layer %d in the README's table) is not "
                         "defined in layer %d's section (lines %d-%d)", line_at(code, def), fn[k], k, k,
                         line_at(code, heading[k]), line_at(code, next) - 1);
    }
    for (k = 0; k <= LAYERS; k++) free(fn[k]);
    free(readme);
    free(code);
}

void suite_layers(void)
{
    test_run("layers: 1, proxies off exactly when the budget holds every blob", test_layer2_boundary);
    test_run("layers: the cache at its limit, and a byte under", test_cache_at_the_limit);
    test_run("layers: 8, points decoded only into room every blob leaves", test_layer9_decoded_points);
    test_run("layers: 2, few rays in flight exactly when every blob fits", test_layer10_rays_in_flight);
    test_run("layers: a ray source over its room is an error", test_source_contract);
    test_run("layers: an interrupt stops the trace between batches", test_interrupt_between_batches);
    test_run("layers: batchrt.c holds one section a layer, in the README's order", test_layer_sections);
}
