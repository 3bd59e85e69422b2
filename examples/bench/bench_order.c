/*
** examples/bench/bench_order.c -- the bottom-level benchmark of layers 10
** and 11 and of proxies in core (README, Benchmarks): `make bench-order`.
**
**   build/bench_order [--scale S] [--rays N] [--repeat R] [--limit P]
**                     [--point-instanced N] [--mesh FILE] [--dir DIR] [--quick]
**
** Three scenes: the instanced landscape and island at --scale (built-in,
** as render makes them) and a mesh (--mesh, by default the shared dragon,
** gunzipped into DIR once; its rows say SKIP when it is absent).  Per
** scene N camera rays (its default view) and N diffuse rays (bounces from
** camera hits, as raygen --kind bounce makes them).  One scene file each
** in DIR, built once and reused while it matches.
**
** Table 1, the bottom level: each scene and ray kind traced in core (no
** memory limit, the paper's scheduler, so every ray is queued and
** batched) and out of core (--limit per cent of the geometry bytes, the
** default scheduler), each with the four uses of the proxy entry --
** neither, clip (layer 10), order (layer 11), both.  Per use: the BVH
** nodes visited per batched ray and the Mrays/s of the batches'
** intersections (testing.h, brt_test_bottom_level), best of R; the speed
** ratio both/neither of each of the R rounds, as a range.  Rounds run the
** four uses in alternating order (forward, then backward), so that a
** drift of the machine's speed favours no use, after one untimed run
** that warms the caches (the OS's of the scene file, the allocator's).
** Table 2, proxies in core: no memory limit, the default scheduler:
** proxies off (layer 1) against brt_trace_options.proxies_in_core; trace
** seconds (best of R), BVH nodes per ray (every walk of a triangle BVH:
** the resident intersections of layer 4 and the batches) and the share of
** proxy tests that culled.
** BVH nodes are those testing.h's counter counts: the nodes of triangle
** BVHs (bvh.c), a batching point's own and, under its instances, their
** prototypes'; not the box trees over the batching points and over a
** point's instances (batchrt.c), which it does not see.
**
** Every run is one thread: the node counter is a plain integer, and the
** bottom-level counters are the plain loop's (testing.h).  Every run's
** hits must equal the first run's of its scene and ray kind, byte for
** byte; else the program says which and exits 1 (a benchmark of wrong
** hits would be meaningless).  Figures only, never pass/fail.
**
** WHY THE TESTING LIBRARY.  The counters are hooks of testing.h, compiled
** only into $(BUILD)/tests/libbatchrt_testing.a (BRT_TESTING), so the
** Makefile links this program with that copy, not with $(LIB).  Its BVH
** walks do one add per node visit (bvh.c, NODE_VISITED) and read the early
** rejection from a variable: the same in every column, so the ratios
** compare like with like.  Absolute Mrays/s are those of that build; make
** bench-embree times the release library.
*/
#include "common.h"
#include "count.h"
#include "input.h"
#include "rays.h"
#include "scenes.h"
#include "testing.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/types.h>
#include <sys/wait.h>
#include <unistd.h>

#ifndef BRT_TESTING
#error "bench_order needs the library's hooks: compile it with -DBRT_TESTING (the Makefile does)"
#endif

static const char *const prog = "bench_order";

#define KINDS 2                 /* camera, diffuse */
#define USES 4                  /* neither, clip, order, both */
#define SCENES 3                /* landscape, island, the mesh */

static const char *const kind_names[KINDS] = {"camera", "diffuse"};
static const char *const use_names[USES] = {"neither", "clip", "order", "both"};

typedef struct options {
    double scale;
    uint64_t rays, repeat, point_instanced;
    double limit_percent;
    const char *mesh, *dir;
    int quick;
} options;

/* One scene of the benchmark, its rays and its first run's hits. */
typedef struct bench_scene {
    const char *name;
    char label[64];
    brt_scene *scene;           /* NULL: skipped (skip says why) */
    char skip[600];
    uint64_t geometry_bytes;
    brt_ray *rays[KINDS];
    brt_hit *reference[KINDS];  /* NULL until the first run */
    brt_hit *hits;
    size_t count;
} bench_scene;

/* What one trace measured. */
typedef struct run_result {
    brt_stats stats;
    uint64_t nodes;             /* BVH node visits, every walk */
    uint64_t bottom_rays, bottom_nodes;
    double bottom_seconds;
} run_result;

static void usage(void)
{
    printf("usage: build/bench_order [options]\n"
           "The bottom level of the batched mode: BVH nodes per batched ray and the batches'\n"
           "Mrays/s with the proxy entry's clip (layer 10) and order (layer 11) on and off,\n"
           "in and out of core; then proxies off against --proxies-in-core without a limit.\n"
           "Scenes: the instanced landscape and island, and a mesh; camera and diffuse rays;\n"
           "one thread; hits checked byte-equal across every run (exit 1 if not).\n"
           "\n"
           "  --scale S            size of the landscape and the island (default 80)\n"
           "  --rays N             rays per kind and scene (default 400000)\n"
           "  --repeat R           timed rounds per row, best taken (default 3)\n"
           "  --limit P            out of core: memory limit in per cent of the geometry\n"
           "                       bytes (default 30)\n"
           "  --point-instanced N  instanced scenes: at most N instanced triangles per\n"
           "                       batching point (default 20000000)\n"
           "  --mesh FILE          the third scene, OBJ or PLY, gzipped or not (default\n"
           "                       ../shared/data/meshes/dragon.obj.gz; its rows say SKIP\n"
           "                       when it is absent)\n"
           "  --dir DIR            scene files and the unzipped mesh (default\n"
           "                       /tmp/batchrt-bench-order); built once, then reused\n"
           "  --quick              a smoke run: --scale 0.05 --rays 4000 --repeat 1 unless given\n"
           "  --help               this text\n");
}

static void parse_options(int argc, char **argv, options *o)
{
    int i, scale_given = 0, rays_given = 0, repeat_given = 0;
    memset(o, 0, sizeof *o);
    o->scale = 80;
    o->rays = 400000;
    o->repeat = 3;
    o->point_instanced = 20000000;
    o->limit_percent = 30;
    o->mesh = "../shared/data/meshes/dragon.obj.gz";
    o->dir = "/tmp/batchrt-bench-order";
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (strcmp(a, "--scale") == 0) {
            o->scale = ex_parse_double(prog, a, ex_option_value(prog, argc, argv, &i), 0.01, EX_SCENE_MAX_SCALE);
            scale_given = 1;
        } else if (strcmp(a, "--rays") == 0) {
            o->rays = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 1, 1u << 26);
            rays_given = 1;
        } else if (strcmp(a, "--repeat") == 0) {
            o->repeat = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 1, 1000);
            repeat_given = 1;
        } else if (strcmp(a, "--limit") == 0)
            o->limit_percent = ex_parse_double(prog, a, ex_option_value(prog, argc, argv, &i), 1, 99);
        else if (strcmp(a, "--point-instanced") == 0)
            o->point_instanced = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, &i), 1, UINT64_MAX);
        else if (strcmp(a, "--mesh") == 0) o->mesh = ex_option_value(prog, argc, argv, &i);
        else if (strcmp(a, "--dir") == 0) o->dir = ex_option_value(prog, argc, argv, &i);
        else if (strcmp(a, "--quick") == 0) o->quick = 1;
        else if (a[0] == '-') ex_unknown_option(prog, a);
        else ex_die(prog, "unexpected argument '%s' (see --help)", a);
    }
    if (o->quick) {
        if (!scale_given) o->scale = 0.05;
        if (!rays_given) o->rays = 4000;
        if (!repeat_given) o->repeat = 1;
    }
}

/* ===================================================================== */
/* The scenes                                                            */
/* ===================================================================== */

static void make_dir(const char *dir)
{
    if (mkdir(dir, 0777) != 0 && errno != EEXIST) ex_die(prog, "%s: cannot create: %s", dir, strerror(errno));
}

static int has_suffix(const char *s, const char *suffix)
{
    size_t n = strlen(s), k = strlen(suffix);
    return n >= k && strcmp(s + n - k, suffix) == 0;
}

/* The mesh as a plain file: itself, or a gzipped one unzipped by gzip into
** dir once (kept: its modification time is the scene file's stamp, so the
** scene file is reused while it stays).  0, with *why, when it is absent. */
static int plain_mesh(const char *mesh, const char *dir, char *path, size_t size, char *why, size_t why_size)
{
    struct stat st;
    const char *base = strrchr(mesh, '/') ? strrchr(mesh, '/') + 1 : mesh;
    char tmp[4300];
    pid_t pid;
    int fd, status;
    if (stat(mesh, &st) != 0) {
        snprintf(why, why_size, "SKIP: %s absent", mesh);
        return 0;
    }
    if (!has_suffix(mesh, ".gz")) {
        snprintf(path, size, "%s", mesh);
        return 1;
    }
    if (snprintf(path, size, "%s/%.*s", dir, (int)(strlen(base) - 3), base) >= (int)size)
        ex_die(prog, "%s: path too long", dir);
    if (stat(path, &st) == 0 && st.st_size > 0) return 1;
    snprintf(tmp, sizeof tmp, "%s.tmp", path);
    fd = open(tmp, O_WRONLY | O_CREAT | O_TRUNC, 0666);
    if (fd < 0) ex_die(prog, "%s: cannot create: %s", tmp, strerror(errno));
    fflush(NULL);
    pid = fork();
    if (pid < 0) ex_die(prog, "cannot start gzip: %s", strerror(errno));
    if (pid == 0) {
        if (dup2(fd, 1) < 0) _exit(127);
        execlp("gzip", "gzip", "-dc", mesh, (char *)NULL);
        _exit(127);
    }
    close(fd);
    if (waitpid(pid, &status, 0) != pid || !WIFEXITED(status) || WEXITSTATUS(status) != 0) {
        unlink(tmp);
        ex_die(prog, "%s: gzip -dc failed", mesh);
    }
    if (rename(tmp, path) != 0) ex_die(prog, "%s: cannot rename: %s", tmp, strerror(errno));
    return 1;
}

/* Camera rays from the scene's view (a built-in's, or raygen's fit of a
** mesh) on a near-square grid, and bounce rays from their hits, traced
** in the world held in memory (raygen's rays of a pbrt file). */
static void make_rays(const options *o, bench_scene *b, const brt_scene_source *source)
{
    brt_world *world;
    brt_error err;
    float bmin[3], bmax[3], eye[3], target[3], fov;
    uint32_t width = (uint32_t)ceil(sqrt((double)o->rays));
    uint32_t height = (uint32_t)((o->rays + width - 1) / width);
    uint64_t rng = 1;
    ex_camera cam;
    int k;
    ex_check(prog, brt_world_build(source, &world, &err), &err);
    brt_world_bounds(world, bmin, bmax);
    if (ex_scene_is_builtin(b->name)) {
        ex_scene_camera(b->name, bmin, bmax, eye, target, &fov);
        ex_camera_look(&cam, eye, target, fov, width, height);
    } else {
        ex_camera_fit(&cam, bmin, bmax, width, height);
    }
    b->count = (size_t)o->rays;
    for (k = 0; k < KINDS; k++)
        if (!(b->rays[k] = malloc(b->count * sizeof *b->rays[k])))
            ex_die(prog, "out of memory for %lu rays", (unsigned long)b->count);
    if (!(b->hits = malloc(b->count * sizeof *b->hits))) ex_die(prog, "out of memory for hits");
    ex_rays_camera(&cam, b->rays[0], b->count, &rng);
    if (!ex_rays_bounce_world(world, &cam, b->rays[1], b->count, &rng))
        ex_die(prog, "%s: no camera ray hits the scene: nothing to bounce from", b->label);
    brt_world_free(world);
}

/* The scene file in dir, reused when it matches the input and options
** (brt_scene_prepare_source), else built from the streams. */
static void open_scene(const options *o, bench_scene *b, const brt_scene_source *source,
                       uint64_t stamp, uint64_t unique)
{
    brt_scene_options sopt;
    brt_error err;
    char path[4200];
    int rebuilt;
    double start = brt_seconds();
    memset(&sopt, 0, sizeof sopt);
    /* One file serves both regimes: the points trace --memory P% would
    ** cut (README, "The default point size"), so the cache out of core
    ** holds a few of them. */
    sopt.point_tris = (uint32_t)ex_default_point_tris(unique, 0, o->limit_percent);
    sopt.point_instanced = source->prototype_count > 0 ? o->point_instanced : 0;
    if ((source->prototype_count > 0
         ? snprintf(path, sizeof path, "%s/%s-s%g-b%u-i%llu.brs", o->dir, b->name, o->scale, sopt.point_tris,
                    (unsigned long long)sopt.point_instanced)
         : snprintf(path, sizeof path, "%s/%s-b%u.brs", o->dir, b->label, sopt.point_tris)) >= (int)sizeof path)
        ex_die(prog, "%s: path too long", o->dir);
    ex_check(prog, brt_scene_prepare_source(source, stamp, path, &sopt, &b->scene, &rebuilt, &err), &err);
    b->geometry_bytes = ex_scene_geometry_bytes(prog, b->scene);
    fprintf(stderr, "%s: %s: %llu unique triangles, %u batching points, geometry %.1f MiB, "
            "scene file %s (%s, %.1f s)\n", prog, b->label, (unsigned long long)unique,
            brt_scene_point_count(b->scene), b->geometry_bytes / 1048576.0, path,
            rebuilt ? "built" : "reused", brt_seconds() - start);
}

static void load_instanced(const options *o, bench_scene *b)
{
    ex_instanced_scene *s;
    brt_scene_source source;
    ex_scene_recipe recipe;
    brt_error err;
    ex_check(prog, ex_instanced_open(b->name, o->scale, 1, &s, &err), &err);
    ex_instanced_source(s, &source);
    snprintf(b->label, sizeof b->label, "%s %g", b->name, o->scale);
    recipe.name = b->name;
    recipe.scale = o->scale;
    recipe.seed = 1;
    /* render's stamp of an instanced built-in ("instance": not the baked scene's) */
    open_scene(o, b, &source, brt_mix64(ex_scene_stamp(&recipe) ^ 0x696E7374616E6365u),
               ex_instanced_unique(s));
    make_rays(o, b, &source);
    ex_instanced_close(s);
}

static void load_mesh(const options *o, bench_scene *b)
{
    brt_scene_source source;
    char path[4200];
    const char *base = strrchr(o->mesh, '/') ? strrchr(o->mesh, '/') + 1 : o->mesh;
    uint64_t stamp;
    brt_error err;
    snprintf(b->label, sizeof b->label, "%.*s", (int)strcspn(base, "."), base);
    if (!plain_mesh(o->mesh, o->dir, path, sizeof path, b->skip, sizeof b->skip)) return;
    memset(&source, 0, sizeof source);
    brt_mesh_file_source(path, &source.world);
    ex_check(prog, brt_scene_source_stamp(path, &stamp, &err), &err);
    open_scene(o, b, &source, stamp, ex_mesh_file_triangles(path));
    make_rays(o, b, &source);
}

/* ===================================================================== */
/* Runs                                                                  */
/* ===================================================================== */

/* One trace of kind's rays, one thread, with the counters read around
** it; its hits held against the first run's. */
static void run(bench_scene *b, int kind, brt_trace_options *opt, const char *what, run_result *out)
{
    uint64_t rays0, nodes0, rays1, nodes1, visits0 = brt_test_node_visits();
    double seconds0, seconds1;
    brt_error err;
    opt->threads = 1;
    brt_test_bottom_level(&rays0, &nodes0, &seconds0);
    ex_check(prog, brt_scene_trace(b->scene, opt, b->rays[kind], b->count, b->hits, &out->stats, &err), &err);
    brt_test_bottom_level(&rays1, &nodes1, &seconds1);
    out->nodes = brt_test_node_visits() - visits0;
    out->bottom_rays = rays1 - rays0;
    out->bottom_nodes = nodes1 - nodes0;
    out->bottom_seconds = seconds1 - seconds0;
    if (!b->reference[kind]) {
        if (!(b->reference[kind] = malloc(b->count * sizeof *b->hits))) ex_die(prog, "out of memory for hits");
        memcpy(b->reference[kind], b->hits, b->count * sizeof *b->hits);
    } else if (memcmp(b->reference[kind], b->hits, b->count * sizeof *b->hits) != 0) {
        size_t i = 0;
        while (memcmp(&b->reference[kind][i], &b->hits[i], sizeof *b->hits) == 0) i++;
        fprintf(stderr, "%s: %s, %s rays, %s: hits differ from the first run's, first at ray %lu: "
                "a benchmark of wrong hits means nothing\n", prog, b->label, kind_names[kind], what,
                (unsigned long)i);
        exit(1);
    }
}

static double ratio(double a, double b)
{
    return b > 0 ? a / b : 0.0;
}

/* The hook counting the batch rays whose walk the clip started after
** their tnear (testing.h: brt_test_on_batch_ray). */
typedef struct clip_count {
    const brt_ray *rays;        /* the traced rays, by tag */
    uint64_t rays_seen, clipped;
} clip_count;

static void count_clipped(void *user, uint32_t point, uint32_t place, uint64_t tag, const brt_ray *ray,
                          uint32_t entry_voxel)
{
    clip_count *c = user;
    (void)point; (void)place; (void)entry_voxel;
    c->rays_seen++;
    c->clipped += ray->tnear > c->rays[tag & ~BRT_TAG_OCCLUSION].tnear;
}

/* One regime's measure: the four uses, R rounds. */
typedef struct regime_result {
    double nodes[USES];         /* BVH nodes per batched ray */
    double best[USES];          /* the batches' Mrays/s, best of R */
    double lo, hi;              /* both / neither over the rounds */
    double clipped;             /* share of batched rays clipped (both uses) */
} regime_result;

static void regime_measure(const options *o, bench_scene *b, int kind, int out_of_core, regime_result *m)
{
    uint64_t batched[USES], r;
    clip_count count;
    int u, i;
    memset(m, 0, sizeof *m);
    memset(&count, 0, sizeof count);
    count.rays = b->rays[kind];
    for (r = 0; r <= o->repeat; r++) {
        double speed[USES];
        for (i = 0; i < USES; i++) {
            brt_trace_options opt;
            run_result res;
            char what[128];
            u = r % 2 == 1 ? i : USES - 1 - i;       /* alternating order */
            memset(&opt, 0, sizeof opt);
            if (out_of_core)
                opt.memory_limit = (uint64_t)((double)b->geometry_bytes * o->limit_percent / 100.0);
            else
                opt.paper_scheduler = 1;
            opt.no_clip = !(u & 1);
            opt.no_order = !(u & 2);
            snprintf(what, sizeof what, "%s, %s", out_of_core ? "out of core" : "in core", use_names[u]);
            /* round 0: one run of both uses, untimed, to warm up and count the clipped rays */
            brt_test_on_batch_ray(r == 0 ? count_clipped : NULL, &count);
            run(b, kind, &opt, what, &res);
            brt_test_on_batch_ray(NULL, NULL);
            if (r == 0) break;
            speed[u] = ratio((double)res.bottom_rays, res.bottom_seconds) * 1e-6;
            if (speed[u] > m->best[u]) m->best[u] = speed[u];
            m->nodes[u] = ratio((double)res.bottom_nodes, (double)res.bottom_rays);
            batched[u] = res.bottom_rays;
        }
        if (r > 0) {
            const double q = ratio(speed[3], speed[0]);
            if (r == 1 || q < m->lo) m->lo = q;
            if (r == 1 || q > m->hi) m->hi = q;
        }
    }
    m->clipped = ratio((double)count.clipped, (double)count.rays_seen);
    for (u = 1; u < USES; u++)
        if (batched[u] != batched[0])   /* layers 10 and 11 change no queue (batchrt.c) */
            fprintf(stderr, "%s: %s, %s rays: %llu batched rays with %s, %llu with neither\n", prog,
                    b->label, kind_names[kind], (unsigned long long)batched[u], use_names[u],
                    (unsigned long long)batched[0]);
}

/* Proxies in core: off (layer 1) against proxies_in_core, no limit, the
** default scheduler, R rounds: the best trace seconds of each, and the
** share of proxy tests that culled. */
static void in_core_measure(const options *o, bench_scene *b, int kind, double best[2], double *culled)
{
    run_result last[2];
    uint64_t r;
    int i;
    best[0] = best[1] = 0;
    for (r = 0; r <= o->repeat; r++)
        for (i = 0; i < 2; i++) {
            const int on = r % 2 == 1 ? i : 1 - i;
            brt_trace_options opt;
            memset(&opt, 0, sizeof opt);
            opt.proxies_in_core = on;
            run(b, kind, &opt, on ? "proxies in core" : "proxies off in core", &last[on]);
            if (r == 0) break;                       /* round 0: one run to warm up, untimed */
            if (r == 1 || last[on].stats.seconds < best[on]) best[on] = last[on].stats.seconds;
        }
    *culled = ratio((double)last[1].stats.proxy_culled, (double)last[1].stats.proxy_tests);
}

/* One regime's cells: nodes per ray neither and clip; Mrays/s of the
** four uses; both/neither's range. */
static void print_regime(const regime_result *m)
{
    printf(" %.1f, %.1f | %.2f, %.2f, %.2f, %.2f | %.2f-%.2f |", m->nodes[0], m->nodes[1], m->best[0], m->best[1],
           m->best[2], m->best[3], m->lo, m->hi);
}

/* The table's row of a scene and ray kind. */
static void scene_row(const options *o, bench_scene *b, int kind)
{
    regime_result out, in;
    double seconds[2], culled;
    regime_measure(o, b, kind, 1, &out);
    regime_measure(o, b, kind, 0, &in);
    in_core_measure(o, b, kind, seconds, &culled);
    printf("| %s | %s | %.0f %% |", b->label, kind_names[kind], 100.0 * out.clipped);
    print_regime(&out);
    print_regime(&in);
    printf(" %.2f (%.0f %%) |\n", ratio(seconds[1], seconds[0]), 100.0 * culled);
    fflush(stdout);
}

int main(int argc, char **argv)
{
    static const char *const names[SCENES] = {"landscape", "island", "mesh"};
    options o;
    bench_scene scenes[SCENES];
    double start = brt_seconds();
    int s, k;

    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    parse_options(argc, argv, &o);
    make_dir(o.dir);
    memset(scenes, 0, sizeof scenes);
    for (s = 0; s < SCENES; s++) {
        scenes[s].name = names[s];
        if (s < 2) load_instanced(&o, &scenes[s]);
        else load_mesh(&o, &scenes[s]);
    }
    brt_test_count_bottom(1);   /* from here one trace at a time, one thread (the rays are made) */

    printf("%llu camera and %llu diffuse rays a scene, one thread; out of core at %g %% of the geometry "
           "bytes, in core with every ray queued (--paper-scheduler); uses of the proxy entry: neither, "
           "clip, order, both; Mrays/s of the batches, best of %llu; proxies in core: trace time with "
           "--proxies-in-core over without, no limit (the share of proxy tests culled):\n\n",
           (unsigned long long)o.rays, (unsigned long long)o.rays, o.limit_percent, (unsigned long long)o.repeat);
    printf("| scene | rays | clipped | out of core: nodes/ray, neither, clip | Mrays/s, the four uses | both / "
           "neither | in core: nodes/ray | Mrays/s | both / neither | proxies in core |\n");
    printf("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n");
    for (s = 0; s < SCENES; s++) {
        if (!scenes[s].scene) {
            printf("| %s | - | %s | | | | | | | |\n", scenes[s].label, scenes[s].skip);
            continue;
        }
        for (k = 0; k < KINDS; k++) scene_row(&o, &scenes[s], k);
    }
    fprintf(stderr, "%s: %.0f s in all\n", prog, brt_seconds() - start);

    for (s = 0; s < SCENES; s++) {
        brt_scene_close(scenes[s].scene);
        for (k = 0; k < KINDS; k++) {
            free(scenes[s].rays[k]);
            free(scenes[s].reference[k]);
        }
        free(scenes[s].hits);
    }
    return 0;
}
