/*
** examples/tools/embree_trace.c -- build/trace on Embree 3 instead of batchrt:
** the same command line, ray and hit files and statistics, so that the two
** hit files can be compared with build/hitdiff (README, "Checking against
** Embree").  Optional: built by "make embree" only, never by "make".
**
**   build/embree_trace MESH RAYS HITS [--direct] [--robust] [--stats FILE]
**
** One Embree triangle geometry (geomID 0) holds the mesh in file order, so
** Embree's primID is batchrt's triangle number.  Rays go one at a time
** through rtcIntersect1 on one thread (the device is created with
** threads=1, so the BVH build is single-threaded like batchrt's too).
** Embree's answer is turned into batchrt's hit record: t is the ray's
** tfar after the call, u and v are Embree's own barycentrics (batchrt uses
** Embree's convention), and a miss is batchrt's miss record.
**
** Where Embree 3 and batchrt define a hit differently (README): batchrt
** counts tnear <= t <= tfar, Embree tnear < t <= tfar; Embree's default
** triangle test (Moeller-Trumbore) is not watertight, its robust mode
** (--robust, RTC_SCENE_FLAG_ROBUST: Pluecker test, conservative box tests)
** is; among hits at equal t batchrt reports the lowest triangle, Embree
** whichever its traversal meets first.  Embree requires 0 <= tnear: a ray
** file with a negative tnear is rejected.  Rays batchrt never hits (NaN,
** infinite or zero direction, tnear > tfar) are written as misses without
** asking Embree, whose behaviour on them is undefined.
**
** --occlusion: rtcOccluded1 instead, and an occlusion file out (one byte
** per ray, 1 occluded, 0 clear; Embree sets tfar to -inf on a hit), the
** file of build/trace --occlusion.
**
** A pbrt-v4 file (".pbrt", examples/lib/pbrt.h) with instances becomes what
** Embree-based builds of the method make of it: the world triangles as
** geometry 0, one scene per prototype (its triangles in stream order, so
** primID is the prototype's triangle number), and one RTC_GEOMETRY_TYPE_
** INSTANCE per instance, attached as geometry 1 + its number, with
** rtcSetGeometryTransform (FLOAT3X4_ROW_MAJOR, brt_instance's layout).
** Embree's instID[0] - 1 is then batchrt's hit.inst, and the hit file the
** instanced one of build/trace.
*/
#include "common.h"
#include "input.h"
#include "tracer.h"

#include <embree3/rtcore.h>

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static const char *const prog = "embree_trace";

typedef struct embree_options {
    ex_tracer_options t;             /* the options of every tracer (tracer.h) */
    int robust;                      /* RTC_SCENE_FLAG_ROBUST */
} embree_options;

static void usage(void)
{
    printf("usage: build/embree_trace MESH RAYS HITS [options]\n"
           "Intersects every ray of RAYS (32-byte records) with the triangles of MESH\n"
           "(OBJ, PLY or a pbrt-v4 .pbrt scene, one rtcInstance per instance) using\n"
           "Embree %s and writes the closest hits to HITS, in the formats and numbering\n"
           "of build/trace.\n"
           "\n"
           "  --direct          accepted for symmetry with build/trace (the only mode)\n"
           "  --occlusion       rtcOccluded1: HITS becomes an occlusion file, one byte per\n"
           "                    ray, 1 occluded, 0 clear (as build/trace --occlusion)\n"
           "  --robust          RTC_SCENE_FLAG_ROBUST: watertight Pluecker triangle test\n"
           "                    and conservative box tests (default: Embree's fast mode)\n"
           "  --stats FILE      write statistics as JSON (the fields of build/trace)\n"
           "  --verbose         print the summary line even when stderr is not a terminal\n"
           "  --help            this text\n"
           "\n"
           "build/trace's batched options (--batched, --point-tris, --proxy-res, --no-proxy,\n"
           "--memory, --scene, --rebuild, --drop-os-cache) are rejected: Embree traces\n"
           "in memory.  Exit status 0 on success, 1 on bad input (nothing is written).\n",
           RTC_VERSION_STRING);
}

/* build/trace's options that only make sense for batchrt's batched mode;
** rejected by name so that a copied command line fails clearly. */
static int is_batched_option(const char *arg)
{
    static const char *const names[] = {"--batched", "--point-tris", "--proxy-res", "--no-proxy",
                                        "--memory", "--scene", "--rebuild", "--drop-os-cache"};
    size_t i;
    for (i = 0; i < sizeof names / sizeof names[0]; i++)
        if (strcmp(arg, names[i]) == 0) return 1;
    return 0;
}

/* embree_trace's own options, beside every tracer's (ex_tracer_parse). */
static int own_option(void *user, int argc, char **argv, int *i)
{
    embree_options *o = user;
    const char *a = argv[*i];
    (void)argc;
    if (strcmp(a, "--direct") == 0) return 1;
    if (strcmp(a, "--robust") == 0) {
        o->robust = 1;
        return 1;
    }
    if (is_batched_option(a))
        ex_die(prog, "%s: not supported: Embree traces in memory (use build/trace for "
               "the batched mode)", a);
    return 0;
}

static void parse_options(int argc, char **argv, embree_options *o)
{
    ex_tracer_command c = {prog, "MESH RAYS HITS", 0, 0, own_option, o};
    memset(o, 0, sizeof *o);
    ex_tracer_parse(&c, argc, argv, &o->t);
}

/* Embree reports errors through a callback; every one is fatal here. */
static void on_embree_error(void *user, enum RTCError code, const char *message)
{
    (void)user;
    ex_die(prog, "Embree error %d: %s", (int)code, message ? message : "(no message)");
}

/* Embree's memory monitor: bytes allocated (positive) and freed (negative)
** while the BVH is built, for the bvh_bytes_per_triangle statistic. */
static ssize_t embree_bytes;

static bool on_embree_memory(void *user, ssize_t bytes, bool post)
{
    (void)user;
    (void)post;
    embree_bytes += bytes;
    return true;
}

static RTCDevice open_device(void)
{
    RTCDevice device = rtcNewDevice("threads=1");
    if (!device)
        ex_die(prog, "rtcNewDevice failed (Embree error %d)", (int)rtcGetDeviceError(NULL));
    rtcSetDeviceErrorFunction(device, on_embree_error, NULL);
    rtcSetDeviceMemoryMonitorFunction(device, on_embree_memory, NULL);
    /* A library built with backface culling would miss every hit on a
    ** back face, which batchrt reports: refuse rather than disagree. */
    if (rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_BACKFACE_CULLING_ENABLED))
        ex_die(prog, "this Embree library was built with backface culling; "
               "batchrt reports hits on both faces");
    return device;
}

/* The mesh as one triangle geometry, copied into Embree-owned buffers
** (rtcSetNewGeometryBuffer pads them for Embree's vector loads). */
static RTCScene build_scene(RTCDevice device, const brt_mesh *mesh, int robust)
{
    RTCScene scene = rtcNewScene(device);
    RTCGeometry geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
    float *vertices = rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0,
                                              RTC_FORMAT_FLOAT3, 3 * sizeof(float),
                                              mesh->vertex_count);
    uint32_t *indices = rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0,
                                                RTC_FORMAT_UINT3, 3 * sizeof(uint32_t),
                                                mesh->triangle_count);
    memcpy(vertices, mesh->positions, (size_t)mesh->vertex_count * 3 * sizeof(float));
    memcpy(indices, mesh->indices, (size_t)mesh->triangle_count * 3 * sizeof(uint32_t));
    rtcCommitGeometry(geom);
    if (rtcAttachGeometry(scene, geom) != 0)
        ex_die(prog, "Embree numbered the only geometry other than 0");
    rtcReleaseGeometry(geom);
    if (robust) rtcSetSceneFlags(scene, RTC_SCENE_FLAG_ROBUST);
    embree_bytes = 0;
    rtcCommitScene(scene);
    return scene;
}

/* ---- instanced input ---- */

/* A gathered triangle stream as one Embree triangle geometry (three
** vertices per triangle, triangle i = primID i). */
static RTCGeometry triangle_geometry(RTCDevice device, const ex_corners *g)
{
    RTCGeometry geom = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_TRIANGLE);
    float *vertices = rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                                              3 * sizeof(float), 3 * g->count);
    uint32_t *indices = rtcSetNewGeometryBuffer(geom, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                                                3 * sizeof(uint32_t), g->count);
    size_t i;
    memcpy(vertices, g->corners, 9 * g->count * sizeof(float));
    for (i = 0; i < 3 * g->count; i++) indices[i] = (uint32_t)i;
    rtcCommitGeometry(geom);
    return geom;
}

typedef struct instancer {
    RTCDevice device;
    RTCScene scene;
    RTCScene *prototypes;
    uint32_t prototype_count;
} instancer;

static brt_result attach_instances(void *user, const brt_instance *instances, uint32_t count,
                                   uint32_t first, brt_error *err)
{
    const instancer *in = user;
    uint32_t i;
    for (i = 0; i < count; i++) {
        RTCGeometry geom;
        if (instances[i].prototype >= in->prototype_count)
            return brt_fail(err, BRT_EARG, "instance %u: prototype %u out of range",
                            (unsigned)(first + i), (unsigned)instances[i].prototype);
        geom = rtcNewGeometry(in->device, RTC_GEOMETRY_TYPE_INSTANCE);
        rtcSetGeometryInstancedScene(geom, in->prototypes[instances[i].prototype]);
        rtcSetGeometryTransform(geom, 0, RTC_FORMAT_FLOAT3X4_ROW_MAJOR, instances[i].xform);
        rtcCommitGeometry(geom);
        rtcAttachGeometryByID(in->scene, geom, 1 + first + i);
        rtcReleaseGeometry(geom);
    }
    return BRT_OK;
}

/* The scene of an instanced input (see the header comment). */
static RTCScene build_instanced_scene(RTCDevice device, const brt_scene_source *src, int robust,
                                      uint64_t *triangles)
{
    instancer in;
    ex_corners g = {NULL, 0, 0};
    brt_error err;
    uint32_t p;
    in.device = device;
    in.scene = rtcNewScene(device);
    in.prototype_count = src->prototype_count;
    in.prototypes = calloc(src->prototype_count + 1, sizeof *in.prototypes);
    if (!in.prototypes) ex_die(prog, "out of memory for %u prototypes", (unsigned)src->prototype_count);
    *triangles = 0;
    if (src->world.run) {
        ex_check(prog, src->world.run(src->world.user, ex_corners_append, &g, &err), &err);
        rtcAttachGeometryByID(in.scene, triangle_geometry(device, &g), 0);
        *triangles += g.count;
    }
    for (p = 0; p < src->prototype_count; p++) {
        g.count = 0;
        ex_check(prog, src->prototype(src->user, p, ex_corners_append, &g, &err), &err);
        in.prototypes[p] = rtcNewScene(device);
        if (robust) rtcSetSceneFlags(in.prototypes[p], RTC_SCENE_FLAG_ROBUST);
        rtcAttachGeometry(in.prototypes[p], triangle_geometry(device, &g));
        rtcCommitScene(in.prototypes[p]);
        *triangles += g.count;
    }
    free(g.corners);
    if (src->instances) ex_check(prog, src->instances(src->user, attach_instances, &in, &err), &err);
    if (robust) rtcSetSceneFlags(in.scene, RTC_SCENE_FLAG_ROBUST);
    embree_bytes = 0;
    rtcCommitScene(in.scene);
    for (p = 0; p < src->prototype_count; p++) rtcReleaseScene(in.prototypes[p]);
    free(in.prototypes);
    return in.scene;
}

/* A negative tnear is a valid batchrt ray but not a valid Embree ray. */
static void check_rays(const char *path, const brt_ray *rays, size_t count)
{
    size_t i;
    for (i = 0; i < count; i++)
        if (rays[i].tnear < 0.0f)
            ex_die(prog, "%s: ray %lu: tnear %g < 0, which Embree 3 does not support",
                   path, (unsigned long)i, (double)rays[i].tnear);
}

/* batchrt's ray as Embree's. */
static void embree_ray(const brt_ray *ray, struct RTCRay *out)
{
    out->org_x = ray->org[0];
    out->org_y = ray->org[1];
    out->org_z = ray->org[2];
    out->dir_x = ray->dir[0];
    out->dir_y = ray->dir[1];
    out->dir_z = ray->dir[2];
    out->tnear = ray->tnear;
    out->tfar = ray->tfar;
    out->time = 0.0f;
    out->mask = 0xFFFFFFFFu;
    out->id = 0;
    out->flags = 0;
}

/* One ray through rtcOccluded1: 1 occluded, 0 clear (and for the rays
** batchrt never hits, 0 without asking Embree). */
static uint8_t occluded_ray(RTCScene scene, const brt_ray *ray)
{
    struct RTCIntersectContext context;
    struct RTCRay r;
    brt_ray_prep prep;

    brt_ray_prepare(ray, &prep);
    if (!prep.valid) return 0;
    rtcInitIntersectContext(&context);
    embree_ray(ray, &r);
    rtcOccluded1(scene, &context, &r);
    return r.tfar == -INFINITY;
}

/* One ray through rtcIntersect1, answered as batchrt's hit record. */
static void trace_ray(RTCScene scene, const brt_ray *ray, brt_hit *hit)
{
    struct RTCIntersectContext context;
    struct RTCRayHit rh;
    brt_ray_prep prep;

    brt_hit_clear(hit);
    brt_ray_prepare(ray, &prep);
    if (!prep.valid) return;
    rtcInitIntersectContext(&context);
    embree_ray(ray, &rh.ray);
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rh.hit.primID = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
    rtcIntersect1(scene, &context, &rh);
    if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) return;
    hit->t = rh.ray.tfar;   /* Embree shortens the ray to its hit */
    hit->prim = rh.hit.primID;
    hit->u = rh.hit.u;
    hit->v = rh.hit.v;
    if (rh.hit.instID[0] != RTC_INVALID_GEOMETRY_ID) hit->inst = rh.hit.instID[0] - 1;
}

static void trace_all(const embree_options *o, const ex_input *input, const brt_ray *rays,
                      size_t count, brt_hit *hits, uint8_t *occluded, brt_stats *stats)
{
    RTCDevice device = open_device();
    RTCScene scene;
    double start = brt_seconds();
    uint64_t triangles;
    size_t i;
    brt_error err;

    ex_progress("building Embree BVH", 0, 1);
    if (input->pbrt) {
        scene = build_instanced_scene(device, &input->source, o->robust, &triangles);
    } else {
        brt_mesh mesh;
        ex_check(prog, brt_mesh_load(input->path, &mesh, &err), &err);
        scene = build_scene(device, &mesh, o->robust);
        triangles = mesh.triangle_count;
        brt_mesh_free(&mesh);
    }
    stats->build_seconds = brt_seconds() - start;
    if (triangles > 0) stats->bvh_bytes_per_triangle = (double)embree_bytes / (double)triangles;

    start = brt_seconds();
    for (i = 0; i < count; i++) {
        /* Progress in slices of 64K rays keeps the clock out of the loop. */
        if ((i & 0xFFFF) == 0) ex_progress("tracing", i, count);
        if (occluded) stats->occlusion_hits += occluded[i] = occluded_ray(scene, &rays[i]);
        else trace_ray(scene, &rays[i], &hits[i]);
    }
    if (occluded) stats->occlusion_rays = count;
    stats->seconds = brt_seconds() - start;
    ex_progress("tracing", count, count);
    ex_progress_end();
    rtcReleaseScene(scene);
    rtcReleaseDevice(device);
}

int main(int argc, char **argv)
{
    embree_options o;
    brt_error err;
    ex_input input;
    brt_ray *rays;
    brt_hit *hits = NULL;
    uint8_t *occluded = NULL;
    size_t count, i;
    brt_stats stats;
    uint64_t hit_count = 0;

    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    parse_options(argc, argv, &o);
    ex_check(prog, brt_rays_read(o.t.rays, &rays, &count, &err), &err);
    check_rays(o.t.rays, rays, count);
    if (o.t.occlusion) occluded = malloc(count ? count : 1);
    else hits = malloc((count ? count : 1) * sizeof *hits);
    if (!hits && !occluded) ex_die(prog, "%s: out of memory for %lu hits", o.t.hits, (unsigned long)count);
    ex_input_open(prog, o.t.input, &input);

    memset(&stats, 0, sizeof stats);
    stats.rays = count;
    trace_all(&o, &input, rays, count, hits, occluded, &stats);
    if (stats.seconds > 0) stats.mrays_per_second = (double)count / stats.seconds * 1e-6;

    if (occluded) ex_check(prog, brt_write_file_atomic(o.t.hits, occluded, count, &err), &err);
    else ex_check(prog, ex_input_write_hits(&input, o.t.hits, hits, count, &err), &err);
    ex_input_close(&input);
    stats.peak_rss_bytes = brt_peak_rss_bytes();
    if (o.t.stats) ex_check(prog, brt_stats_write_json(o.t.stats, &stats, &err), &err);
    if (o.t.verbose || isatty(2)) {
        for (i = 0; hits && i < count; i++) hit_count += hits[i].prim != BRT_NO_PRIM;
        hit_count += stats.occlusion_hits;
        fprintf(stderr, "embree_trace: %llu rays, %llu %s, build %.3f s, trace %.3f s, "
                "%.2f Mrays/s%s\n", (unsigned long long)count, (unsigned long long)hit_count,
                hits ? "hits" : "occluded",
                stats.build_seconds, stats.seconds, stats.mrays_per_second,
                o.robust ? " (robust)" : "");
    }
    free(hits);
    free(occluded);
    free(rays);
    return 0;
}
