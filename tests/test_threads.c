/*
** tests/test_threads.c -- the threads contract (README
** "Threads"): at 1, 2 and 7 threads (more than this machine's cores, and
** more than some runs have work), every hit equals the direct mode's, the
** scheduler's counts and the order of its finished calls are equal, scene
** files are equal byte for byte, and the programs write equal hit files,
** images and statistics counts.  Also the geometry cache's resident memory
** under a limit (its buffers go back to the system on eviction).  "make
** tsan" runs the tests named "threads" under ThreadSanitizer.
*/
#include "test.h"
#include "util.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const unsigned thread_counts[] = {1, 2, 7, 0};   /* 0: one per online core */
#define RUNS (sizeof thread_counts / sizeof thread_counts[0])

/* A soup of n triangles and rays of every kind, with their reference hits
** (brt_bvh_intersect one ray after another) and normals. */
typedef struct soup {
    tu_scene scene;
    brt_ray *rays;
    brt_hit *hits;
    float *normals;
    size_t count;
} soup;

static int soup_make(soup *s, uint32_t n, size_t per_kind, uint64_t seed)
{
    float lo[3], hi[3];
    uint64_t st = seed;
    brt_bvh *bvh = NULL;
    size_t i;
    int kind;
    memset(s, 0, sizeof *s);
    tu_random_soup(&s->scene, &st, n, 0.05f);
    tu_scene_bounds(&s->scene, lo, hi);
    s->count = per_kind * TU_RAY_KINDS;
    s->rays = malloc(s->count * sizeof *s->rays);
    s->hits = malloc(s->count * sizeof *s->hits);
    s->normals = calloc(3 * s->count, sizeof *s->normals);
    if (!s->rays || !s->hits || !s->normals) return 0;
    for (kind = 0; kind < TU_RAY_KINDS; kind++)
        for (i = 0; i < per_kind; i++)
            tu_make_ray(&s->scene, lo, hi, kind, &st, &s->rays[(size_t)kind * per_kind + i]);
    if (brt_bvh_build(s->scene.pos, s->scene.idx, s->scene.tcount, NULL, &bvh) != BRT_OK) return 0;
    for (i = 0; i < s->count; i++) {
        brt_hit_clear(&s->hits[i]);
        brt_bvh_intersect_normal(bvh, &s->rays[i], &s->hits[i], s->normals + 3 * i);
    }
    brt_bvh_free(bvh);
    return 1;
}

static void soup_free(soup *s)
{
    tu_scene_free(&s->scene);
    free(s->rays);
    free(s->hits);
    free(s->normals);
}

/* ---- direct tracing ------------------------------------------------------ */

static void test_bvh_trace(void)
{
    soup s;
    brt_bvh *bvh = NULL;
    brt_hit *hits;
    float *normals;
    uint64_t *tags;
    size_t run, counts[] = {0, 1, 1023, 1025, 20000}, c, i;
    CHECK(soup_make(&s, 3000, 5000, test_seed()), "soup");
    CHECK(brt_bvh_build(s.scene.pos, s.scene.idx, s.scene.tcount, NULL, &bvh) == BRT_OK, "build");
    hits = malloc(s.count * sizeof *hits);
    normals = malloc(3 * s.count * sizeof *normals);
    tags = malloc(s.count * sizeof *tags);
    CHECK(hits && normals && tags, "out of memory");
    for (i = 0; i < s.count; i++) tags[i] = i % 3 == 0 ? BRT_TAG_OCCLUSION : 0;
    for (run = 0; run < RUNS && !test_failed(); run++)
        for (c = 0; c < sizeof counts / sizeof counts[0] && !test_failed(); c++) {
            size_t n = counts[c];
            memset(hits, 0xAB, s.count * sizeof *hits);
            brt_bvh_trace(bvh, s.rays, NULL, n, hits, normals, thread_counts[run]);
            EXPECT(memcmp(hits, s.hits, n * sizeof *hits) == 0 &&
                   memcmp(normals, s.normals, 3 * n * sizeof *normals) == 0,
                   "%u threads, %zu rays: hits or normals differ from one ray after another",
                   thread_counts[run], n);
            brt_bvh_trace(bvh, s.rays, NULL, n, hits, NULL, thread_counts[run]);
            for (i = 0; i < n; i++)
                if (memcmp(&hits[i], &s.hits[i], sizeof *hits) != 0) break;
            EXPECT(i == n, "%u threads, %zu rays, no normals: ray %zu differs", thread_counts[run], n, i);
            /* every third ray an occlusion ray: brt_ray_source's record,
            ** from brt_bvh_occluded one ray at a time */
            brt_bvh_trace(bvh, s.rays, tags, n, hits, NULL, thread_counts[run]);
            for (i = 0; i < n; i++) {
                brt_hit want = s.hits[i];
                if (tags[i]) {
                    brt_hit_clear(&want);
                    if (brt_bvh_occluded(bvh, &s.rays[i])) want.t = 0.0f, want.prim = 0;
                }
                if (memcmp(&hits[i], &want, sizeof want) != 0) break;
            }
            EXPECT(i == n, "%u threads, %zu rays of both kinds: ray %zu differs", thread_counts[run], n, i);
        }
    free(hits);
    free(normals);
    free(tags);
    brt_bvh_free(bvh);
    soup_free(&s);
}

/* ---- batched tracing ----------------------------------------------------- */

static brt_scene *soup_scene(const soup *s, uint32_t point_tris, unsigned threads, const char *name)
{
    return tu_build_scene(&s->scene, point_tris, 32, threads, tu_scratch(name));
}

/* Every count of the statistics (times vary; nothing else may). */
static int same_counts(const brt_stats *a, const brt_stats *b)
{
    return a->rays == b->rays && a->batching_points == b->batching_points &&
           a->geometry_bytes == b->geometry_bytes && a->disk_bytes_read == b->disk_bytes_read &&
           a->batch_loads == b->batch_loads && a->cache_peak_bytes == b->cache_peak_bytes &&
           a->memory_limit == b->memory_limit && a->proxy_bytes == b->proxy_bytes &&
           a->proxy_tests == b->proxy_tests && a->proxy_culled == b->proxy_culled &&
           a->visits == b->visits && a->queued_visits == b->queued_visits &&
           a->resident_visits == b->resident_visits && a->oversized_loads == b->oversized_loads;
}

/* A source that hands its rays out in slices, and for every finished ray
** that hit, a follow-up ray (a bounce: the ray mirrored at the hit); it
** logs the finished calls in order, so two runs can be compared call by
** call, as a path tracer that gives out slots by completion would see. */
typedef struct logging_source {
    const brt_ray *rays;
    size_t count, next;
    brt_ray *bounces;
    uint64_t *bounce_tags;
    size_t bounce_count, bounce_cap;
    uint64_t *log;              /* tag of each finished call, in order */
    brt_hit *log_hits;
    size_t logged, log_cap;
} logging_source;

static size_t log_next(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    logging_source *l = user;
    size_t n = 0;
    while (n < max && l->bounce_count > 0) {
        l->bounce_count--;
        rays[n] = l->bounces[l->bounce_count];
        tags[n++] = l->bounce_tags[l->bounce_count];
    }
    while (n < max && n < 700 && l->next < l->count) {
        rays[n] = l->rays[l->next];
        tags[n++] = l->next++;
    }
    return n;
}

static void log_finished(void *user, const brt_ray *ray, const brt_hit *hit, const float normal[3],
                         uint32_t visits, uint64_t tag)
{
    logging_source *l = user;
    (void)normal;
    (void)visits;
    if (l->logged < l->log_cap) {
        l->log[l->logged] = tag;
        l->log_hits[l->logged++] = *hit;
    }
    /* One bounce per primary ray that hit: from just before the hit,
    ** back the way it came (it hits near where it left, in the same
    ** batching point or its neighbours). */
    if (tag < l->count && hit->prim != BRT_NO_PRIM && l->bounce_count < l->bounce_cap) {
        brt_ray b = *ray;
        int a;
        for (a = 0; a < 3; a++) {
            b.org[a] = ray->org[a] + 0.999f * hit->t * ray->dir[a];
            b.dir[a] = -ray->dir[a];
        }
        b.tnear = 0.0f;
        b.tfar = INFINITY;
        l->bounces[l->bounce_count] = b;
        l->bounce_tags[l->bounce_count++] = l->count + tag;
    }
}

static int log_init(logging_source *l, const soup *s)
{
    memset(l, 0, sizeof *l);
    l->rays = s->rays;
    l->count = s->count;
    l->bounce_cap = s->count;
    l->log_cap = 2 * s->count;
    l->bounces = malloc(l->bounce_cap * sizeof *l->bounces);
    l->bounce_tags = malloc(l->bounce_cap * sizeof *l->bounce_tags);
    l->log = malloc(l->log_cap * sizeof *l->log);
    l->log_hits = malloc(l->log_cap * sizeof *l->log_hits);
    return l->bounces && l->bounce_tags && l->log && l->log_hits;
}

static void log_free(logging_source *l)
{
    free(l->bounces);
    free(l->bounce_tags);
    free(l->log);
    free(l->log_hits);
}

/* The settings under which the schedule is compared: memory limits that
** hold everything, part, and less than one batching point; proxies on
** and off; the paper's scheduler; few and many rays in flight. */
typedef struct setting {
    const char *name;
    uint64_t memory;            /* in batching points' average bytes; 0: none */
    int no_proxy, paper_scheduler;
    uint32_t in_flight;
} setting;

static const setting settings[] = {
    {"no limit", 0, 0, 0, 0},
    {"limit 1/4, proxies", 4, 0, 0, 1000},
    {"limit 1/2, proxies", 2, 0, 0, 4000},
    {"limit 1/8, no proxies", 8, 1, 0, 0},
    {"limit 1/4, no proxies", 4, 1, 0, 300},
    {"limit 1/4, queue resident", 4, 0, 1, 0},
    {"limit below one point", 1000, 0, 0, 64},
};

static void test_batched_counts(void)
{
    soup s;
    brt_scene *scene;
    size_t k, run, i;
    CHECK(soup_make(&s, 4000, 1500, test_seed() + 1), "soup");
    CHECK((scene = soup_scene(&s, 100, 1, "threads.brs")) != NULL, "scene");
    for (k = 0; k < sizeof settings / sizeof settings[0] && !test_failed(); k++) {
        const setting *set = &settings[k];
        logging_source first;
        brt_stats first_stats;
        int have_first = 0;
        memset(&first, 0, sizeof first);
        memset(&first_stats, 0, sizeof first_stats);
        for (run = 0; run < RUNS && !test_failed(); run++) {
            logging_source l;
            brt_ray_source source;
            brt_trace_options opt;
            brt_stats stats;
            brt_error err;
            CHECK(log_init(&l, &s), "out of memory");
            memset(&opt, 0, sizeof opt);
            opt.threads = thread_counts[run];
            opt.no_proxy = set->no_proxy;
            opt.paper_scheduler = set->paper_scheduler;
            opt.rays_in_flight = set->in_flight;
            if (set->memory > 0) {
                /* The geometry bytes are known after a first trace. */
                brt_stats probe;
                CHECK(brt_scene_trace(scene, NULL, NULL, 0, NULL, &probe, &err) == BRT_OK, "probe");
                opt.memory_limit = probe.geometry_bytes / set->memory + probe.proxy_bytes;
            }
            source.next_rays = log_next;
            source.finished = log_finished;
            source.user = &l;
            CHECK(brt_scene_trace_stream(scene, &opt, &source, &stats, &err) == BRT_OK,
                  "%s, %u threads: %s", set->name, thread_counts[run], err.message);
            /* Primary hits equal the direct mode's. */
            for (i = 0; i < l.logged; i++)
                if (l.log[i] < s.count && memcmp(&l.log_hits[i], &s.hits[l.log[i]], sizeof s.hits[0]) != 0)
                    break;
            EXPECT(i == l.logged, "%s, %u threads: ray %llu differs from direct", set->name,
                   thread_counts[run], (unsigned long long)(i < l.logged ? l.log[i] : 0));
            if (run == 0) {
                first = l;
                have_first = 1;
                first_stats = stats;
                EXPECT(set->memory == 0 || stats.batch_loads > stats.batching_points,
                       "%s: no batching point was read twice (the limit does not bite)", set->name);
                continue;
            }
            EXPECT(same_counts(&stats, &first_stats),
                   "%s: counts at %u threads differ from 1 thread (loads %llu vs %llu, bytes %llu vs "
                   "%llu, proxy tests %llu vs %llu, queued %llu vs %llu, resident %llu vs %llu)",
                   set->name, thread_counts[run], (unsigned long long)stats.batch_loads,
                   (unsigned long long)first_stats.batch_loads, (unsigned long long)stats.disk_bytes_read,
                   (unsigned long long)first_stats.disk_bytes_read, (unsigned long long)stats.proxy_tests,
                   (unsigned long long)first_stats.proxy_tests, (unsigned long long)stats.queued_visits,
                   (unsigned long long)first_stats.queued_visits, (unsigned long long)stats.resident_visits,
                   (unsigned long long)first_stats.resident_visits);
            EXPECT(l.logged == first.logged && memcmp(l.log, first.log, l.logged * sizeof *l.log) == 0 &&
                   memcmp(l.log_hits, first.log_hits, l.logged * sizeof *l.log_hits) == 0,
                   "%s: the finished calls at %u threads come in another order than at 1", set->name,
                   thread_counts[run]);
            log_free(&l);
        }
        if (have_first) log_free(&first);
    }
    brt_scene_close(scene);
    soup_free(&s);
}

/* ---- scene files ----------------------------------------------------------- */

static void test_scene_bytes(void)
{
    soup s;
    brt_mesh mesh;
    unsigned char *first = NULL;
    size_t first_size = 0, run;
    /* 50-triangle points, and buckets of 600 triangles: many windows of
    ** points, and the split of buckets larger than memory. */
    static const uint32_t buckets[] = {0, 600};
    size_t b;
    CHECK(soup_make(&s, 5000, 1, test_seed() + 2), "soup");
    mesh = tu_mesh_view(&s.scene);
    for (b = 0; b < 2 && !test_failed(); b++) {
        free(first);
        first = NULL;
        for (run = 0; run < RUNS && !test_failed(); run++) {
            brt_scene_options opt;
            brt_error err;
            unsigned char *bytes;
            size_t size;
            memset(&opt, 0, sizeof opt);
            opt.point_tris = 50;
            opt.proxy_res = 16;
            brt_test_build_sizes(0, buckets[b]);
            opt.threads = thread_counts[run];
            CHECK(brt_scene_build(&mesh, &opt, 7, tu_scratch("bytes.brs"), &err) == BRT_OK,
                  "build: %s", err.message);
            CHECK((bytes = tu_slurp(tu_scratch("bytes.brs"), &size)) != NULL, "read back");
            if (run == 0) {
                first = bytes;
                first_size = size;
                continue;
            }
            EXPECT(size == first_size && memcmp(bytes, first, size) == 0,
                   "bucket %u: the scene file at %u threads differs from 1 thread's", buckets[b],
                   thread_counts[run]);
            free(bytes);
        }
    }
    free(first);
    soup_free(&s);
}

/* ---- the programs ---------------------------------------------------------- */

static unsigned char *slurp_scratch(const char *name, size_t *size)
{
    return tu_slurp(tu_scratch(name), size);
}

/* The statistics JSON without its timing and memory lines (times vary;
** peak RSS grows with the threads' stacks). */
static void strip_times(char *json)
{
    char *line = json, *out = json;
    while (*line) {
        char *end = strchr(line, '\n');
        size_t n = end ? (size_t)(end - line + 1) : strlen(line);
        if (!strstr(line, "seconds\"") && !strstr(line, "mrays_per_second") &&
            !strstr(line, "peak_rss_bytes") && !strstr(line, "mrays")) {
            memmove(out, line, n);
            out += n;
        }
        line += n;
    }
    *out = 0;
}

/* Runs "COMMAND --threads N ARGS" at each thread count and compares the
** outputs named in files with the first run's. */
static void same_outputs(const char *command, const char *args, const char *const *files,
                         size_t nfiles)
{
    unsigned char *first[4] = {0};
    size_t first_size[4] = {0}, run, f;
    for (run = 0; run < RUNS && !test_failed(); run++) {
        int status = tu_run("%s --threads %u %s", command, thread_counts[run], args);
        EXPECT(status == 0, "%u threads: exit %d: %s", thread_counts[run], status, tu_last_stderr());
        for (f = 0; f < nfiles && !test_failed(); f++) {
            size_t size;
            unsigned char *bytes = slurp_scratch(files[f], &size);
            CHECK(bytes, "%s not written", files[f]);
            if (strstr(files[f], ".json")) {
                strip_times((char *)bytes);
                size = strlen((char *)bytes);
            }
            if (run == 0) {
                first[f] = bytes;
                first_size[f] = size;
                continue;
            }
            EXPECT(size == first_size[f] && memcmp(bytes, first[f], size) == 0,
                   "%s at %u threads differs from 1 thread's", files[f], thread_counts[run]);
            free(bytes);
        }
    }
    for (f = 0; f < nfiles; f++) free(first[f]);
}

static void test_programs(void)
{
    static const char *const trace_files[] = {"t.hits", "t.json"};
    static const char *const render_files[] = {"r.png", "r.json", "heat.png"};
    const char *mesh = test_shared_mesh("bunny_tiny.obj");
    if (!mesh) {
        test_skip("../shared/data/meshes/bunny_tiny.obj absent");
        return;
    }
    char trace[600];
    snprintf(trace, sizeof trace, "trace %s @/t.rays @/t.hits", mesh);
    CHECK(tu_run("raygen %s @/t.rays --kind bounce --count 20000 --seed 5", mesh) == 0, "raygen");
    same_outputs(trace, "--direct --stats @/t.json", trace_files, 2);
    /* --rebuild: each run builds the scene file with its threads too. */
    same_outputs(trace, "--batched --point-tris 100 --memory 40K --scene @/t.brs --rebuild "
                 "--stats @/t.json", trace_files, 2);
    same_outputs("render landscape --scale 0.2 --point-tris 500 --memory 25% --spp 2 --width 48 "
                 "--height 32 --rays-in-flight 700", "--scene @/r.brs --out @/r.png "
                 "--heatmap @/heat.png --stats @/r.json", render_files, 3);
    same_outputs("render landscape --scale 0.2 --spp 2 --width 48 --height 32 --direct",
                 "--out @/r.png --stats @/r.json", render_files, 2);
}

/* ---- the geometry cache's resident memory ------------------------------------ */

/* A render of the crown (a plain scene) from a scene file at --memory 3M
** that reads its ~0.9 MiB blobs (40,000 triangles) many times: peak RSS at most the
** limit + the README's fixed costs (300 B per path in flight, 512 B per
** batching point, 40 B per pixel) + 8 MiB of program, libraries and stacks
** (measured: 7.8 MiB in all).  With the blobs posix_memalign'd and freed,
** glibc's heap keeps freed blobs resident and this fails (16.8 MiB against
** a bound of 12.5; with blobs of 15,000 triangles the difference, 12.1
** against 7.1, stayed inside the bound, so they would not catch it). */
static void test_cache_rss(void)
{
    char *json;
    unsigned long long peak = 0, limit = 0, points = 0, loads = 0;
    const char *p;
    double bound;
    if (!tu_rss_is_meaningful()) return;
    CHECK(tu_run("render crown --scale 6 --point-tris 40000 --width 1 --height 1 --spp 1 "
                 "--scene @/rss.brs --out @/rss.png") == 0, "build: %s", tu_last_stderr());
    CHECK(tu_run("render crown --scale 6 --point-tris 40000 --width 240 --height 135 --spp 4 "
                 "--memory 3M --rays-in-flight 1024 --scene @/rss.brs --out @/rss.png "
                 "--stats @/rss.json") == 0, "render: %s", tu_last_stderr());
    CHECK((json = (char *)slurp_scratch("rss.json", NULL)) != NULL, "stats");
    if ((p = strstr(json, "\"peak_rss_bytes\":"))) peak = strtoull(p + 17, NULL, 10);
    if ((p = strstr(json, "\"memory_limit\":"))) limit = strtoull(p + 15, NULL, 10);
    if ((p = strstr(json, "\"batching_points\":"))) points = strtoull(p + 18, NULL, 10);
    if ((p = strstr(json, "\"batch_loads\":"))) loads = strtoull(p + 14, NULL, 10);
    free(json);
    CHECK(peak > 0 && limit > 0, "no peak_rss_bytes or memory_limit in the statistics");
    CHECK(loads > 3 * points, "only %llu loads of %llu batching points: the limit does not bite",
          loads, points);
    bound = (double)limit + 300.0 * 1024 + 512.0 * (double)points + 40.0 * 240 * 135 + 8.0 * 1048576;
    EXPECT((double)peak <= bound, "peak RSS %.1f MiB > limit %.1f MiB + fixed costs = %.1f MiB",
           (double)peak / 1048576, (double)limit / 1048576, bound / 1048576);
}

void suite_threads(void)
{
    test_run("threads: brt_bvh_trace == one ray after another, both kinds, 1/2/7 threads", test_bvh_trace);
    test_run("threads: batched counts and finished order equal at 1/2/7 threads", test_batched_counts);
    test_run("threads: scene files equal at 1/2/7 threads", test_scene_bytes);
    test_run("threads: trace and render outputs equal at 1/2/7 threads and --threads 0", test_programs);
    test_run("cache: peak RSS within the limit + fixed costs while reloading", test_cache_rss);
}
