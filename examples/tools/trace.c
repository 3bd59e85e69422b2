/*
** examples/tools/trace.c -- intersect a ray file with a mesh and write the hit
** file (formats in README.md and batchrt.h).
**
**   build/trace MESH RAYS HITS [--direct | --batched] [options]
**
** --direct (the default) builds one triangle BVH over the whole mesh in
** memory and traces ray by ray: the reference every other mode of batchrt
** must match byte for byte.  --batched splits the mesh into batching points
** stored in a scene file (built once, reused while the mesh and settings
** are unchanged), casts each ray against the voxel proxies before queueing
** it, and reads geometry through the geometry cache (Pharr et al. 1997;
** Molenaar and Eisemann 2020).  It never holds the mesh: the scene file is
** built from the mesh file as a triangle stream (brt_scene_build_stream),
** and a scene file that matches is used without reading the mesh at all.
** Only --direct loads the whole mesh, and says so when it is larger than
** the --memory given.
**
** --occlusion asks the other question of every ray: is any triangle hit
** within [tnear, tfar]?  The output is then an occlusion file, one byte per
** ray (1 occluded, 0 clear), Embree's rtcOccluded1; both modes write the
** same bytes (brt_bvh_occluded, brt_scene_occluded).
**
** --follow N tells ray N's journey through the method on stdout, one line
** a step (brt_trace_options.follow): each batching point its walk enters,
** the proxy's verdict, intersected in memory or queued, the load that
** serves its queue, the triangles' answer, and the final hit.
**
** SIGINT and SIGTERM stop the scene build (which removes its temporary
** files), the batched trace before its next batch (brt_trace_options
** .interrupt), or, at the latest, the program before it writes any
** output; the exit status is then 128 + the signal number.
**
** Everything is validated (options, mesh, ray file) before any output file
** is written, and outputs are written atomically, so a failed run never
** leaves a half-written file behind.
*/
#include "common.h"
#include "input.h"
#include "tracer.h"

#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static const char *const prog = "trace";

typedef struct trace_options {
    ex_tracer_options t;             /* the options of every tracer (tracer.h) */
    int batched;                     /* --batched instead of --direct */
    int no_inner;                    /* batched without inner proxies */
    int no_decode;                   /* batched without decoded points (layer 8) */
    int rebuild;                     /* rebuild the scene file even if current */
    int drop_os_cache;               /* cold reads (brt_trace_options) */
    int follow_given;                /* --follow N */
    uint64_t follow;                 /* the ray followed */
} trace_options;

static void usage(void)
{
    printf("usage: build/trace MESH RAYS HITS [options]\n"
           "Intersects every ray of RAYS (32-byte records) with the triangles of MESH\n"
           "(OBJ, PLY or a pbrt-v4 .pbrt scene, instances included) and writes the closest\n"
           "hits to HITS (16-byte records; with instances, the instanced hit file: a\n"
           "16-byte header and 20-byte records that name the instance).\n"
           "\n"
           "  --occlusion       occlusion queries instead: HITS becomes an occlusion file,\n"
           "                    one byte per ray, 1 when a triangle is hit within\n"
           "                    [tnear, tfar], else 0 (Embree's rtcOccluded1)\n"
           "  --direct          one BVH over the whole mesh in memory (default)\n"
           "  --batched         batching points, proxies and geometry cache\n"
           "  --point-tris N    triangles per batching point, N >= 1 (batched; default: the\n"
           "                    mesh's triangles / max(8, 4 / the --memory share of its\n"
           "                    blobs), at least 100000; README, \"The default point size\")\n"
           "  --rays-in-flight N  rays the batched mode works on at once (default: 4096 when\n"
           "                    --memory holds every batching point, else 1048576)\n"
           "  --proxy-res R     proxy voxel resolution, a power of two in 2..1024 (default 128)\n"
           "  --no-proxy        batched mode without voxel proxies\n"
           "  --no-inner        batched occlusion rays without inner proxies\n"
           "  --no-decode       batched points stay quantized in memory (default: decoded\n"
           "                    to float nodes when the memory holds them beside every blob)\n"
           "  --memory SIZE     geometry-cache budget, e.g. 512M (suffix K, M, G; default 1G)\n"
           "  --scene FILE      scene file for the batched mode (default: in $BRT_SCENE_DIR,\n"
           "                    $XDG_CACHE_HOME/batchrt or ~/.cache/batchrt)\n"
           "  --rebuild         rebuild the scene file even when it is up to date\n"
           "  --drop-os-cache   cold reads: keep the scene file out of the OS cache, so\n"
           "                    every load reads the device\n"
           "  --paper-scheduler queue rays at batching points in memory too (the paper's\n"
           "                    scheduler; default: intersect there at once)\n"
           "  --no-clip         a queued ray's walk in its point starts at tnear (default:\n"
           "                    where it entered the proxy); no byte changes\n"
           "  --no-order        a batch's rays are intersected in queue order (default:\n"
           "                    sorted by the voxel where they entered the proxy); the same\n"
           "  --proxies-in-core consult the proxies when --memory holds every point too,\n"
           "                    also before intersecting at a point in memory\n"
           "  --follow N        print ray N's journey through the method on stdout, one\n"
           "                    line a step (batched; N counts from 0)\n"
           "  --threads N       threads (default 0: all cores); no byte or count changes\n"
           "  --stats FILE      write statistics as JSON\n"
           "  --verbose         print the summary line even when stderr is not a terminal\n"
           "  --help            this text\n"
           "\n"
           "Both modes write byte-identical hit (and occlusion) files.  Exit status 0 on success, 1 on\n"
           "bad input (nothing is written then).\n");
}

/* trace's own options, beside every tracer's (ex_tracer_parse). */
static int own_option(void *user, int argc, char **argv, int *i)
{
    trace_options *o = user;
    const char *a = argv[*i];
    if (strcmp(a, "--direct") == 0) o->batched = 0;
    else if (strcmp(a, "--batched") == 0) o->batched = 1;
    else if (strcmp(a, "--no-inner") == 0) o->no_inner = 1;
    else if (strcmp(a, "--no-decode") == 0) o->no_decode = 1;
    else if (strcmp(a, "--rebuild") == 0) o->rebuild = 1;
    else if (strcmp(a, "--drop-os-cache") == 0) o->drop_os_cache = 1;
    else if (strcmp(a, "--follow") == 0) {
        o->follow = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, i), 0, UINT64_MAX >> 1);
        o->follow_given = 1;
    }
    else return 0;
    return 1;
}

static void parse_options(int argc, char **argv, trace_options *o)
{
    ex_tracer_command c = {prog, "MESH RAYS HITS", 1, 1u << 26, own_option, o};
    memset(o, 0, sizeof *o);
    ex_tracer_defaults(&o->t);
    ex_tracer_parse(&c, argc, argv, &o->t);
    if (o->follow_given && !o->batched)
        ex_die(prog, "--follow needs --batched (the direct mode has no batching points)");
}

/* ---- --follow: one ray's journey ---- */

static void print_hit(const brt_hit *hit)
{
    if (hit->prim == BRT_NO_PRIM) printf("no hit");
    else printf("triangle %u at t = %.9g", hit->prim, hit->t);
}

/* One line per step (brt_step_kind), in the method's words. */
static void follow_print(void *user, uint64_t tag, const brt_step *s)
{
    int occlusion = (tag & BRT_TAG_OCCLUSION) != 0;
    (void)user;
    switch (s->kind) {
    case BRT_STEP_ENTER:
        printf("  enter      point %u, its box entered at t = %.9g\n", s->point, s->t);
        break;
    case BRT_STEP_INNER:
        printf("  inner      point %u: its inner proxy is hit, the ray is occluded\n", s->point);
        break;
    case BRT_STEP_RESIDENT:
        printf("  resident   point %u: in memory, intersected at once (visit %u)\n", s->point,
               s->visits + 1);
        break;
    case BRT_STEP_PROXY_HIT:
        printf("  proxy      point %u: hit, first voxel at t = %.9g\n", s->point, s->t);
        break;
    case BRT_STEP_PROXY_MISS:
        printf("  proxy      point %u: miss, skipped without a load\n", s->point);
        break;
    case BRT_STEP_QUEUED:
        printf("  queued     at point %u (visit %u)\n", s->point, s->visits);
        break;
    case BRT_STEP_LOAD:
        if (s->bytes) printf("  load       point %u: %llu bytes read from disk\n", s->point,
                             (unsigned long long)s->bytes);
        else printf("  load       point %u: already in memory\n", s->point);
        break;
    case BRT_STEP_TRIANGLES:
        printf("  triangles  point %u: ", s->point);
        if (occlusion) printf(s->hit.prim == BRT_NO_PRIM ? "not occluded\n" : "occluded\n");
        else if (s->hit.prim == BRT_NO_PRIM) printf("no hit so far\n");
        else {
            printf("closest so far ");
            print_hit(&s->hit);
            printf("\n");
        }
        break;
    case BRT_STEP_FINISHED:
        printf("  finished   ");
        if (occlusion) printf(s->hit.prim == BRT_NO_PRIM ? "not occluded" : "occluded");
        else print_hit(&s->hit);
        printf(", %u visit%s\n", s->visits, s->visits == 1 ? "" : "s");
        break;
    }
}

static void follow_header(uint64_t n, const brt_ray *r, int occlusion)
{
    printf("ray %llu (%s): origin %.9g %.9g %.9g, direction %.9g %.9g %.9g, t in [%.9g, %.9g]\n",
           (unsigned long long)n, occlusion ? "occlusion" : "closest hit", r->org[0], r->org[1],
           r->org[2], r->dir[0], r->dir[1], r->dir[2], r->tnear, r->tfar);
}

#define SLICE ((size_t)1 << 18)

/* What the direct mode traces with: a mesh's BVH or a pbrt scene's world. */
typedef struct direct_tracer {
    const brt_bvh *bvh;
    const brt_world *world;
} direct_tracer;

static void direct_trace(const direct_tracer *d, const brt_ray *rays, const uint64_t *tags,
                         size_t n, brt_hit *hits, unsigned threads)
{
    if (d->world) brt_world_trace(d->world, rays, tags, n, hits, NULL, threads);
    else brt_bvh_trace(d->bvh, rays, tags, n, hits, NULL, threads);
}

/* Direct mode: one BVH over the whole mesh (or the world of a pbrt
** scene), then every ray through it, with the statistics of README.md
** (cache fields stay 0). */
static void trace_direct(const ex_input *in, const trace_options *o, const brt_ray *rays,
                         size_t count, brt_hit *hits, uint8_t *occluded, brt_stats *stats)
{
    direct_tracer d = {NULL, NULL};
    brt_bvh *bvh = NULL;
    brt_world *world = NULL;
    brt_mesh mesh;
    brt_hit *scratch = NULL;
    uint64_t *tags = NULL;
    double start = brt_seconds();
    size_t i;
    brt_error err;

    ex_progress("building BVH", 0, 1);
    if (in->pbrt) {
        d.world = world = ex_input_world(prog, in);
    } else {
        ex_check(prog, brt_mesh_load(in->path, &mesh, &err), &err);
        ex_note_mesh_memory(prog, &mesh, o->t.memory_given ? o->t.memory : 0);
        ex_check(prog, brt_bvh_build(mesh.positions, mesh.indices, mesh.triangle_count, NULL, &bvh),
                 NULL);
        if (mesh.triangle_count > 0)
            stats->bvh_bytes_per_triangle = (double)brt_bvh_memory_bytes(bvh) / (double)mesh.triangle_count;
        brt_mesh_free(&mesh);
        d.bvh = bvh;
    }
    stats->build_seconds = brt_seconds() - start;

    start = brt_seconds();
    /* Occlusion rays are traced as such (tags) into scratch records, which
    ** become the file's bytes: brt_bvh_trace's record has prim 0 when
    ** occluded, the miss record when clear. */
    if (occluded) {
        scratch = malloc(SLICE * sizeof *scratch);
        tags = malloc(SLICE * sizeof *tags);
        if (!scratch || !tags) ex_die(prog, "out of memory for a slice of occlusion rays");
        for (i = 0; i < SLICE; i++) tags[i] = BRT_TAG_OCCLUSION;
    }
    /* Progress (and the interrupt flag) in slices of 256K rays, each
    ** traced by all threads. */
    for (i = 0; i < count; i += SLICE) {
        size_t n = count - i < SLICE ? count - i : SLICE, k;
        if (ex_interrupted()) ex_die_interrupted(prog);
        ex_progress("tracing", i, count);
        direct_trace(&d, rays + i, tags, n, occluded ? scratch : hits + i, o->t.threads);
        for (k = 0; occluded && k < n; k++) {
            occluded[i + k] = scratch[k].prim != BRT_NO_PRIM;
            stats->occlusion_hits += occluded[i + k];
        }
    }
    if (occluded) stats->occlusion_rays = count;
    stats->seconds = brt_seconds() - start;
    ex_progress("tracing", count, count);
    ex_progress_end();
    brt_bvh_free(bvh);
    brt_world_free(world);
    free(scratch);
    free(tags);
}

/* Batched mode: the scene file (reused, or built from the mesh file as a
** stream by brt_scene_prepare), then the scheduler. */
static void trace_batched(const ex_input *in, const trace_options *o, const brt_ray *rays,
                          size_t count, brt_hit *hits, uint8_t *occluded, brt_stats *stats)
{
    brt_scene_options scene_opt;
    brt_trace_options trace_opt;
    brt_scene *scene;
    brt_error err;
    char default_path[4096];
    const char *path = ex_tracer_scene_path(prog, &o->t, default_path, sizeof default_path);
    double start = brt_seconds();
    brt_result r;
    int rebuilt;
    memset(&scene_opt, 0, sizeof scene_opt);
    scene_opt.point_tris = (uint32_t)o->t.point_tris;
    scene_opt.proxy_res = (uint32_t)o->t.res;
    scene_opt.interrupt = ex_catch_interrupts();
    scene_opt.threads = o->t.threads;
    if (o->rebuild && unlink(path) != 0 && errno != ENOENT)
        ex_die(prog, "%s: cannot remove: %s", path, strerror(errno));
    ex_progress("preparing scene", 0, 1);
    scene = ex_input_scene(prog, in, path, &scene_opt, &rebuilt);
    memset(&trace_opt, 0, sizeof trace_opt);
    ex_tracer_trace_options(&o->t, &trace_opt);
    trace_opt.no_inner = o->no_inner;
    trace_opt.no_decode = o->no_decode;
    trace_opt.drop_os_cache = o->drop_os_cache;
    trace_opt.interrupt = scene_opt.interrupt;
    if (o->follow_given) {
        if (o->follow >= count)
            ex_die(prog, "%s: --follow %llu: the file holds %lu rays", o->t.rays,
                   (unsigned long long)o->follow, (unsigned long)count);
        trace_opt.follow = follow_print;
        trace_opt.follow_tag = o->follow | (occluded ? BRT_TAG_OCCLUSION : 0);
        follow_header(o->follow, &rays[o->follow], occluded != NULL);
    }
    ex_progress("tracing", 0, 1);
    if (occluded)
        r = brt_scene_occluded(scene, &trace_opt, rays, count, occluded, stats, &err);
    else
        r = brt_scene_trace(scene, &trace_opt, rays, count, hits, stats, &err);
    ex_check(prog, r, &err);
    ex_progress_end();
    stats->build_seconds = rebuilt ? brt_seconds() - start - stats->seconds : 0.0;
    if (stats->oversized_loads > 0)
        fprintf(stderr, "trace: note: %llu loads of a batching point larger than the memory "
                "budget%s (each held alone)\n", (unsigned long long)stats->oversized_loads,
                o->t.no_proxy ? "" : " left after the proxies");
    if (o->t.verbose || isatty(2))
        fprintf(stderr, "trace: scene %s (%s), %llu batching points of <= %llu triangles\n", path,
                rebuilt ? "built" : "reused", (unsigned long long)stats->batching_points,
                (unsigned long long)o->t.point_tris);
    brt_scene_close(scene);
}

/* The statistics, and for a pbrt file what it skipped ("skipped"); a
** failure removes the hits too (a run that fails leaves no output). */
static void write_stats(const ex_input *in, const char *path, const char *hits_path,
                        const brt_stats *stats)
{
    char skipped[1024] = "", extra[1100] = "";
    brt_error err;
    if (in->pbrt) {
        ex_json_escape(ex_pbrt_skipped(in->pbrt), skipped, sizeof skipped);
        snprintf(extra, sizeof extra, "  \"skipped\": \"%s\"", skipped);
    }
    if (ex_stats_write(path, stats, extra, &err) != BRT_OK) {
        unlink(hits_path);
        ex_die(prog, "%s", err.message);
    }
}

static void print_summary(const brt_hit *hits, const brt_stats *stats)
{
    uint64_t i, hit_count = stats->occlusion_hits;
    for (i = 0; hits && i < stats->rays; i++) hit_count += hits[i].prim != BRT_NO_PRIM;
    fprintf(stderr, "trace: %llu rays, %llu %s, build %.3f s, trace %.3f s, %.2f Mrays/s\n",
            (unsigned long long)stats->rays, (unsigned long long)hit_count,
            hits ? "hits" : "occluded", stats->build_seconds, stats->seconds, stats->mrays_per_second);
}

int main(int argc, char **argv)
{
    trace_options o;
    brt_error err;
    ex_input in;
    brt_ray *rays;
    brt_hit *hits = NULL;
    uint8_t *occluded = NULL;
    size_t count;
    brt_stats stats;

    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    parse_options(argc, argv, &o);
    ex_catch_interrupts();
    ex_check(prog, brt_rays_read(o.t.rays, &rays, &count, &err), &err);
    if (o.t.occlusion) occluded = malloc(count ? count : 1);
    else hits = malloc((count ? count : 1) * sizeof *hits);
    if (!hits && !occluded) ex_die(prog, "%s: out of memory for %lu hits", o.t.hits, (unsigned long)count);

    memset(&stats, 0, sizeof stats);
    ex_input_open(prog, o.t.input, &in);
    if (o.batched) {
        ex_tracer_point_size(&in, &o.t);
        trace_batched(&in, &o, rays, count, hits, occluded, &stats);
    } else {
        stats.rays = count;
        trace_direct(&in, &o, rays, count, hits, occluded, &stats);
        if (stats.seconds > 0) stats.mrays_per_second = (double)count / stats.seconds * 1e-6;
    }

    if (ex_interrupted()) ex_die_interrupted(prog);
    if (occluded) ex_check(prog, brt_write_file_atomic(o.t.hits, occluded, count, &err), &err);
    else ex_check(prog, ex_input_write_hits(&in, o.t.hits, hits, count, &err), &err);
    /* A run that fails leaves no output at all: the hits go if the
    ** statistics cannot be written. */
    stats.peak_rss_bytes = brt_peak_rss_bytes();
    if (o.t.stats) write_stats(&in, o.t.stats, o.t.hits, &stats);
    ex_input_close(&in);
    if (o.t.verbose || isatty(2)) print_summary(hits, &stats);
    free(hits);
    free(occluded);
    free(rays);
    return 0;
}
