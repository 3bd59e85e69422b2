/*
** examples/tools/render.c -- a unidirectional path tracer on batchrt's batched
** traversal: the program of Molenaar and Eisemann (2020), "Conservative Ray
** Batching using Geometry Proxies", on the scheduler of Pharr et al.
** (1997), "Rendering complex scenes with memory-coherent ray tracing".
**
**   build/render [SCENE] [--scale S] [--spp N] [--width W] [--height H]
**                [--memory SIZE|P%] [--no-proxy] [--direct] [--compare] ...
**
** SCENE is an OBJ/PLY file, a pbrt-v4 file (.pbrt, instances included) or
** a built-in scene: the crown, or the instanced landscape and island
** (examples/lib/scenes.h; default: the landscape at scale 1, about 100
** thousand unique and 6 million instanced triangles).
**
** THE RENDERER
** Lambert materials lit by a sky and a sun: a disc of a given direction,
** angular radius and radiance.  The built-in instanced scenes colour each
** prototype and world part by the hit's (instance, prim)
** (ex_instanced_colour: bark, leaves, grass, rock, sand, sea); everything
** else, and every scene with --grey, is the paper's homogeneous grey
** (albedo 0.8).  A path ends when it escapes, after MAX_DEPTH bounces, or
** by Russian roulette.
**
** Next-event estimation (the default): at every hit that may go on (below
** MAX_DEPTH) one shadow ray -- an occlusion ray, BRT_TAG_OCCLUSION -- goes
** toward a point drawn uniformly on the sun's disc (a cone of solid angle
** W = 2 pi (1 - cos r)); when it is clear the hit gains
** throughput * albedo / pi * sun * cos * W.  Sun and sky are split so that
** nothing is counted twice: an escaping ray then adds the sky only, the
** sun comes only through the shadow rays.  --no-nee is the estimator
** without shadow rays: escaping rays add the sky and, inside the disc, the
** sun.  Both estimate the same sum over the same path depths (a shadow ray
** is cast exactly where the path could go on and find the sun), so they
** converge to the same image (tests/test_render.c checks the means).  A
** path waits for its shadow ray before it bounces on, so it has one ray in
** flight at a time and the number of rays in flight stays constant.  The rays go
** to the scheduler as a stream (brt_scene_trace_stream): the scheduler asks
** for rays when it has free slots and hands back each finished one with
** its hit and geometric normal; a path that bounces gives its next ray on
** the next request, so the number of paths in flight stays constant (as
** in Pharr et al. and the paper).  --direct traces the same paths against one
** in-memory BVH (brt_bvh_intersect_normal), the reference.
**
** DETERMINISM (README.md, "Rendering")
** Rays finish in an order that depends on the schedule, so nothing may
** depend on that order:
**   - every random number is a hash of (pixel, sample, bounce, dimension),
**     never the next value of a shared stream;
**   - each pixel sums its samples in 64-bit fixed point, and integer
**     addition is associative.
** Each hit is the same bytes in every mode (batchrt's contract), so every
** path makes the same decisions, and --direct, batched with or without
** proxies, any memory limit and any number of rays in flight write
** byte-identical images.  tests/test_render.c checks that.
**
** THE HEATMAP (the paper's Fig. 1)
** Batching points visited per sample in each pixel: the scheduler reports
** with each finished ray how many batching points it visited (queued at,
** or intersected at once because their geometry was in memory), and each
** path adds its rays' counts to its pixel.  examples/lib/report.c draws
** the map, and prints the table of --compare.
**
** OUT OF CORE FROM END TO END
** The batched modes never hold the mesh.  The scene file is built from a
** triangle stream (brt_scene_build_stream): a mesh file read as the build
** consumes it, or a built-in scene made as it is consumed (ex_scene_source,
** one object at a time).  Everything else -- the bounds for the default
** camera and the offsets, the triangle count -- comes from the opened
** scene file.  A built-in scene's file goes to the default scene folder
** (ex_scene_folder) under a name made of the scene name, scale, seed and
** the build options, with a stamp made of the same and the generator's
** version (ex_scene_stamp), so it is built once and reused without making
** the scene again.  Only --direct and the direct run of --compare load the
** whole mesh, and say so when it is larger than --memory.
**
** INTERRUPTS
** SIGINT and SIGTERM set a flag (ex_catch_interrupts): the scene build
** polls it and removes its temporary files; the renderer stops starting
** paths, and the program exits non-zero before writing any output.
*/
#include "input.h"
#include "rays.h"
#include "report.h"
#include "scenes.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

static const char *const prog = "render";

#define ALBEDO 0.8
#define MAX_DEPTH 8           /* bounces; a path ends at its 8th hit */
#define ROULETTE_DEPTH 3      /* Russian roulette from the 3rd hit on */
#define FIXED_ONE 4294967296.0 /* 2^32: the fixed-point unit of a pixel sum */
/* Caps one addition to a pixel (no overflow).  A path adds at most
** MAX_DEPTH + 1 times (a shadow ray per hit, the escape), so a pixel sum
** stays below 9 * MAX_SPP * SAMPLE_CLAMP * FIXED_ONE = 9 * 2^58 < 2^64.
** Above the sun's radiance (throughputs stay <= 1 under the roulette), so
** the cap never biases --no-nee against next-event estimation. */
#define SAMPLE_CLAMP 1024.0
#define MAX_SPP 65536
#define SUN_RADIUS 3.0        /* degrees, default */
#define SUN_RADIANCE 500.0    /* default: sun irradiance 4.3 at normal incidence */
#define DIRECT_CHUNK 4096     /* rays per batch in --direct mode */
#define PI 3.14159265358979323846
#define EXPOSURE 0.3          /* a sunlit surface is about 2 */

/* ===================================================================== */
/* Options                                                               */
/* ===================================================================== */

typedef struct options {
    const char *input;            /* mesh file or built-in scene name */
    double scale;
    uint64_t seed, spp, width, height, point_tris, res, rays_in_flight;
    uint64_t point_instanced;     /* --point-instanced; 0: no such limit */
    uint64_t memory;              /* bytes; 0: no limit */
    uint64_t disk_speed;          /* --disk-speed, bytes per second; 0: the device's */
    uint64_t threads;             /* --threads; 0: all cores */
    double memory_percent;        /* > 0: the limit is this share of the geometry bytes */
    int no_inner;
    int no_clip, no_order, proxies_in_core;   /* brt_trace_options' */
    int no_proxy, paper_scheduler, exact_proxy, direct, compare, have_camera, drop_os_cache;
    int exact_voxels;             /* --exact-voxels: brt_scene_options.exact_voxels */
    int have_width, have_height;   /* given: a pbrt file's Film does not set them */
    int no_nee, have_sun, grey;
    float eye[3], target[3], fov;
    float sun[3];                 /* --sun: toward the sun (any length) */
    double sun_radius, sun_radiance;
    double heat_max;              /* colour scale maximum; 0: the image's maximum */
    const char *out, *heatmap, *stats, *scene;
    const char *pfm, *reference;  /* --pfm, --reference: linear images */
} options;

static void usage(void)
{
    printf("usage: build/render [SCENE] [options]\n"
           "Path traces a mesh file (OBJ/PLY), a pbrt-v4 file (.pbrt) or a built-in scene\n"
           "(crown; landscape and island, instanced; default landscape) on the out-of-core\n"
           "batched traversal.\n"
           "\n"
           "  --scale S            size of a built-in scene: about 100000*S unique triangles\n"
           "                       (the instanced scenes: about 6 million instanced per unit)\n"
           "  --seed N             seed of a built-in scene (default 1)\n"
           "  --spp N              samples per pixel (default 8)\n"
           "  --width W            image width (default 320; a pbrt file: its Film's)\n"
           "  --height H           image height (default 180; a pbrt file: its Film's)\n"
           "  --camera E:T:F       eye ex,ey,ez : target tx,ty,tz : field of view in degrees\n"
           "  --sun X,Y,Z          direction toward the sun, y up (default: one per built-in\n"
           "                       scene; 0.48,0.62,0.62 for mesh files)\n"
           "  --sun-radius DEG     the sun's angular radius (default 3)\n"
           "  --sun-radiance V     its radiance (default 500; sky about 0.5)\n"
           "  --no-nee             no shadow rays: only escaping rays find the sun\n"
           "  --grey               the paper's homogeneous grey Lambert (albedo 0.8) instead\n"
           "                       of the built-in scenes' colours\n"
           "                       (default: next-event estimation toward the sun)\n"
           "  --memory SIZE|P%%     geometry memory limit, e.g. 64M, or P %% of the geometry\n"
           "                       bytes (default: no limit); proxies count against it\n"
           "  --point-tris N       triangles per batching point (instanced: those of the distinct\n"
           "                       prototypes it uses); default: the unique triangles / max(8,\n"
           "                       4 / the --memory share of the geometry), at least 100000\n"
           "  --point-instanced N  instanced scenes: a batching point holds at most N\n"
           "                       instanced triangles (default: no such limit)\n"
           "  --proxy-res R        proxy resolution, a power of two (default 128)\n"
           "  --no-proxy           queue rays at every box they enter (Pharr et al.)\n"
           "  --no-inner           shadow rays do not consult the inner proxies\n"
           "  --paper-scheduler    queue rays at batching points in memory too (the paper's\n"
           "                       scheduler; default: intersect there at once)\n"
           "  --no-clip            a queued ray's walk in its point starts at tnear (default:\n"
           "                       where it entered the proxy); no byte changes\n"
           "  --no-order           a batch's rays are intersected in queue order (default:\n"
           "                       sorted by where they entered the proxy); the same\n"
           "  --proxies-in-core    consult the proxies when --memory holds the scene too\n");
    printf("  --exact-proxy        analysis: a perfect proxy (an exact test against the\n"
           "                       triangles, all read first and not counted)\n"
           "  --exact-voxels       analysis: instances' proxies built by testing every\n"
           "                       triangle (slow; the same voxels; its own scene file)\n"
           "  --rays-in-flight N   paths traced at once (default 262144)\n"
           "  --threads N          threads (default 0: all cores); no byte changes\n"
           "  --drop-os-cache      cold reads: keep the scene file out of the OS cache, so\n"
           "                       every load reads the device\n"
           "  --disk-speed SIZE    model a slower disk: each read lasts at least its bytes\n"
           "                       / SIZE per second (e.g. 100M: about a hard disk)\n"
           "  --batched            batched traversal (the default)\n"
           "  --direct             one in-memory BVH instead: the reference\n"
           "  --compare            batched without and with proxies (and direct): prints a\n"
           "                       table; --heatmap X.png then writes X-noproxy.png and\n"
           "                       X-proxy.png, --stats X.json writes X.json and X-noproxy.json\n"
           "  --out FILE.png       the image (default render.png)\n"
           "  --heatmap FILE.png   batching points visited per sample (paper's Fig. 1)\n"
           "  --heat-max V         top of the heatmap's colour scale (default: 99.5th percentile)\n"
           "  --stats FILE.json    statistics (trace's fields plus spp, paths, ...)\n"
           "  --pfm FILE.pfm       the image before tone mapping: each pixel's mean radiance\n"
           "                       (Portable Float Map, little-endian)\n"
           "  --reference REF.pfm  print the RMSE of this image's mean radiance against REF\n"
           "                       (a --pfm of a long render), also \"rmse\" in --stats\n"
           "  --scene FILE         the scene file (default: in the scene folder, reused)\n"
           "  --help               this text\n"
           "\n"
           "Every mode and setting writes the same image, byte for byte.\n");
}

/* "x,y,z" into v; returns the text after it, or NULL. */
static const char *parse_vector(const char *text, float v[3])
{
    int used = 0;
    if (sscanf(text, "%f,%f,%f%n", &v[0], &v[1], &v[2], &used) != 3 || used == 0) return NULL;
    if (!isfinite(v[0]) || !isfinite(v[1]) || !isfinite(v[2])) return NULL;
    return text + used;
}

static void parse_camera(const char *text, options *o)
{
    const char *p = parse_vector(text, o->eye);
    int used = 0;
    if (p && *p == ':') p = parse_vector(p + 1, o->target);
    else p = NULL;
    if (!p || *p != ':' || sscanf(p + 1, "%f%n", &o->fov, &used) != 1 || p[1 + used] != 0
        || !(o->fov > 0 && o->fov < 180)
        || (o->eye[0] == o->target[0] && o->eye[1] == o->target[1] && o->eye[2] == o->target[2]))
        ex_die(prog, "--camera: expected ex,ey,ez:tx,ty,tz:fov with eye != target and "
               "0 < fov < 180, got '%s'", text);
    o->have_camera = 1;
}

static void parse_sun(const char *text, options *o)
{
    const char *p = parse_vector(text, o->sun);
    if (!p || *p != 0 || (o->sun[0] == 0 && o->sun[1] == 0 && o->sun[2] == 0))
        ex_die(prog, "--sun: expected a nonzero direction x,y,z, got '%s'", text);
    o->have_sun = 1;
}

static void parse_memory(const char *text, options *o)
{
    size_t n = strlen(text);
    if (n > 1 && text[n - 1] == '%') {
        char number[64];
        if (n >= sizeof number) ex_die(prog, "--memory: bad percentage '%s'", text);
        memcpy(number, text, n - 1);
        number[n - 1] = 0;
        o->memory_percent = ex_parse_double(prog, "--memory", number, 0.001, 100000);
    } else {
        o->memory = ex_parse_size(prog, "--memory", text);
    }
}

static int is_option(const char *arg, const char *name) { return strcmp(arg, name) == 0; }

/* Outputs are written under a temporary name and renamed over the target
** (brt_write_file_atomic): that would replace a device such as /dev/null
** by a plain file, so only plain files (or new names) are accepted. */
static void check_output(const char *path)
{
    struct stat st;
    if (path && stat(path, &st) == 0 && !S_ISREG(st.st_mode))
        ex_die(prog, "%s: not a regular file; outputs replace their target", path);
}

static void parse_options(int argc, char **argv, options *o)
{
    int i;
    memset(o, 0, sizeof *o);
    o->input = "landscape";
    o->scale = 1;
    o->seed = 1;
    o->spp = 8;
    o->width = 320;
    o->height = 180;
    /* 0: trace's rule, from the scene and the limit (point_size) */
    o->point_tris = 0;
    o->res = 128;
    o->rays_in_flight = 1u << 18;
    o->sun_radius = SUN_RADIUS;
    o->sun_radiance = SUN_RADIANCE;
    o->out = "render.png";
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
#define VALUE ex_option_value(prog, argc, argv, &i)
        if (is_option(a, "--scale")) o->scale = ex_parse_double(prog, a, VALUE, 0.001, EX_SCENE_MAX_SCALE);
        else if (is_option(a, "--seed")) o->seed = ex_parse_u64(prog, a, VALUE, 0, UINT64_MAX);
        else if (is_option(a, "--spp")) o->spp = ex_parse_u64(prog, a, VALUE, 1, MAX_SPP);
        else if (is_option(a, "--width")) o->width = ex_parse_u64(prog, a, VALUE, 1, 16384), o->have_width = 1;
        else if (is_option(a, "--height")) o->height = ex_parse_u64(prog, a, VALUE, 1, 16384), o->have_height = 1;
        else if (is_option(a, "--camera")) parse_camera(VALUE, o);
        else if (is_option(a, "--sun")) parse_sun(VALUE, o);
        else if (is_option(a, "--sun-radius")) o->sun_radius = ex_parse_double(prog, a, VALUE, 0.01, 45);
        else if (is_option(a, "--sun-radiance")) o->sun_radiance = ex_parse_double(prog, a, VALUE, 0, 1000);
        else if (is_option(a, "--no-nee")) o->no_nee = 1;
        else if (is_option(a, "--grey")) o->grey = 1;
        else if (is_option(a, "--memory")) parse_memory(VALUE, o);
        else if (is_option(a, "--point-tris")) o->point_tris = ex_parse_u64(prog, a, VALUE, 1, UINT32_MAX);
        else if (is_option(a, "--point-instanced"))
            o->point_instanced = ex_parse_u64(prog, a, VALUE, 1, UINT64_MAX);
        else if (is_option(a, "--proxy-res")) o->res = ex_parse_resolution(prog, a, VALUE);
        else if (is_option(a, "--rays-in-flight"))
            o->rays_in_flight = ex_parse_u64(prog, a, VALUE, 1, 1u << 26);
        else if (is_option(a, "--threads")) o->threads = ex_parse_u64(prog, a, VALUE, 0, BRT_MAX_THREADS);
        else if (is_option(a, "--heat-max")) o->heat_max = ex_parse_double(prog, a, VALUE, 1e-9, 1e9);
        else if (is_option(a, "--out")) o->out = VALUE;
        else if (is_option(a, "--heatmap")) o->heatmap = VALUE;
        else if (is_option(a, "--stats")) o->stats = VALUE;
        else if (is_option(a, "--pfm")) o->pfm = VALUE;
        else if (is_option(a, "--reference")) o->reference = VALUE;
        else if (is_option(a, "--scene")) o->scene = VALUE;
        else if (is_option(a, "--no-proxy")) o->no_proxy = 1;
        else if (is_option(a, "--no-inner")) o->no_inner = 1;
        else if (is_option(a, "--paper-scheduler")) o->paper_scheduler = 1;
        else if (is_option(a, "--no-clip")) o->no_clip = 1;
        else if (is_option(a, "--no-order")) o->no_order = 1;
        else if (is_option(a, "--proxies-in-core")) o->proxies_in_core = 1;
        else if (is_option(a, "--exact-proxy")) o->exact_proxy = 1;
        else if (is_option(a, "--exact-voxels")) o->exact_voxels = 1;
        else if (is_option(a, "--direct")) o->direct = 1;
        else if (is_option(a, "--batched")) o->direct = 0;
        else if (is_option(a, "--compare")) o->compare = 1;
        else if (is_option(a, "--drop-os-cache")) o->drop_os_cache = 1;
        else if (is_option(a, "--disk-speed")) o->disk_speed = ex_parse_size(prog, a, VALUE);
        else if (a[0] == '-') ex_unknown_option(prog, a);
        else o->input = a;
#undef VALUE
    }
    if (o->direct && (o->heatmap || o->compare))
        ex_die(prog, "--direct has no batching points: no --heatmap or --compare with it");
    if (o->direct && o->disk_speed)
        ex_die(prog, "--direct reads no geometry from disk: no --disk-speed with it");
    check_output(o->out);
    check_output(o->heatmap);
    check_output(o->stats);
    check_output(o->pfm);
}

/*
** THE INTEGRATOR, from here to "The scene", read top to bottom:
** deterministic random numbers, light and surfaces, the paths (the ray
** source the scheduler pulls from, and what each finished ray does to its
** path), and the two tracers that run them, batched and direct.  The rest
** of the file opens the input, and writes the image, the heat map
** (examples/lib/report.c draws it) and the statistics.
*/

/* ===================================================================== */
/* Deterministic random numbers                                          */
/* ===================================================================== */

/* Random dimensions of one bounce. */
enum { DIM_PIXEL_X, DIM_PIXEL_Y, DIM_DIRECTION_R, DIM_DIRECTION_PHI, DIM_ROULETTE,
       DIM_SUN_Z, DIM_SUN_PHI };

/* A counter-based generator: the number of (pixel, sample, bounce,
** dimension) is a hash of that key alone (brt_mix64), uniform in [0, 1)
** with 24 bits, so it is the same whatever order the paths are traced in.
** Chained mixing keeps keys that differ in one field apart. */
static double random_at(uint32_t pixel, uint32_t sample, uint32_t bounce, uint32_t dim)
{
    uint64_t h = brt_mix64(((uint64_t)pixel << 32 | sample) + 0x9E3779B97F4A7C15u);
    h = brt_mix64(h ^ ((uint64_t)bounce << 32 | dim));
    return (double)(h >> 40) * (1.0 / 16777216.0);
}

/* ===================================================================== */
/* Light and surfaces                                                    */
/* ===================================================================== */

/* The sun: a disc of directions within its angular radius of dir. */
typedef struct sun_light {
    double dir[3];          /* unit, toward the sun */
    double cos_max;         /* cos of the angular radius */
    double solid_angle;     /* 2 pi (1 - cos_max) */
    double radiance[3];
} sun_light;

/* The sky seen along unit direction d, without the sun: a gradient from a
** bright horizon to a blue zenith, and a dark ground below the horizon
** (the world beyond the scene, dark so that surfaces stand out). */
static void sky_radiance(const float d[3], double rgb[3])
{
    static const double zenith[3] = {0.12, 0.22, 0.50}, horizon[3] = {0.45, 0.50, 0.58};
    static const double ground[3] = {0.10, 0.09, 0.08};
    double up = d[1], a = sqrt(fabs(up));
    int k;
    for (k = 0; k < 3; k++) rgb[k] = (1 - a) * horizon[k] + a * (up >= 0 ? zenith[k] : ground[k]);
}

/* Nonzero when direction d (any length) lies inside the sun's disc. */
static int sees_sun(const sun_light *sun, const float d[3])
{
    double len = sqrt((double)d[0] * d[0] + (double)d[1] * d[1] + (double)d[2] * d[2]);
    return len > 0 && (sun->dir[0] * d[0] + sun->dir[1] * d[1] + sun->dir[2] * d[2]) / len
                          >= sun->cos_max;
}

/* The Lambert bounce from the hit of ray `in` (ex_lambert_bounce); the
** hit point comes from t, as batched mode has no mesh in memory. */
static int lambert_bounce(const brt_ray *in, const brt_hit *hit, const float normal[3],
                          double diagonal, double u1, double u2, brt_ray *out)
{
    double n[3], p[3];
    int k;
    for (k = 0; k < 3; k++) {
        n[k] = normal[k];
        p[k] = (double)in->org[k] + (double)hit->t * in->dir[k];
    }
    return ex_lambert_bounce(p, n, in->dir, diagonal, u1, u2, out);
}

/* ===================================================================== */
/* Paths: the ray source of the scheduler                                */
/* ===================================================================== */

typedef struct path_state {
    uint32_t pixel, sample, bounce;   /* the random key; bounce = hits so far */
    double weight[3];                 /* throughput: product of albedos / roulette survival */
    brt_ray ray;                      /* the next ray, while the path is pending */
    brt_ray shadow;                   /* the shadow ray, while it is pending */
    double light[3];                  /* what the shadow ray adds when clear */
    int in_shadow_step;               /* the pending ray is the shadow ray */
    int goes_on;                      /* after it, the path bounces with ray */
    double luminance;                 /* added so far (sample_moments) */
} path_state;

/* What one render needs to know. */
typedef struct render_job {
    ex_camera camera;
    uint32_t spp;
    double diagonal;                  /* of the scene's bounds: the offset scale */
    uint32_t paths_in_flight;
    double scene_seconds;             /* building the scene file (0: reused) */
    uint64_t disk_speed;              /* modelled, bytes per second; 0: none */
    sun_light sun;
    double sun_radius;                /* degrees (sun.cos_max is what renders) */
    int nee;                          /* next-event estimation (shadow rays) */
    unsigned threads;                 /* --threads (0: all cores) */
    const ex_instanced_scene *palette; /* colours by (inst, prim), or NULL: grey */
} render_job;

/* Sums over finished samples of their luminance (the mean of r, g, b of
** what the path added) and its square: the image's mean and its standard
** error, for comparing estimators (tests/test_render.c).  A measurement
** in double precision: its last digits may depend on the schedule, unlike
** the image, which is summed in fixed point. */
typedef struct sample_moments {
    double sum, sum_sq;
    uint64_t count;
} sample_moments;

typedef struct renderer {
    const render_job *job;
    path_state *paths;                 /* paths_in_flight of them; tag = index */
    uint32_t *idle, idle_count;        /* path slots without a path */
    uint32_t *pending, pending_count;  /* paths whose next ray awaits next_rays */
    uint64_t started, finished, total; /* path number = sample * pixels + pixel */
    uint64_t *sums;                    /* 3 per pixel, fixed point (FIXED_ONE) */
    uint64_t *visits;                  /* batching points visited per pixel, or NULL */
    sample_moments moments;            /* of the samples' luminance */
} renderer;

static void renderer_init(renderer *r, const render_job *job, int count_visits)
{
    size_t pixels = (size_t)job->camera.width * job->camera.height;
    uint32_t i, n = job->paths_in_flight;
    memset(r, 0, sizeof *r);
    r->job = job;
    r->total = (uint64_t)pixels * job->spp;
    r->paths = malloc((size_t)n * sizeof *r->paths);
    r->idle = malloc((size_t)n * sizeof *r->idle);
    r->pending = malloc((size_t)n * sizeof *r->pending);
    r->sums = calloc(3 * pixels, sizeof *r->sums);
    if (count_visits) r->visits = calloc(pixels, sizeof *r->visits);
    if (!r->paths || !r->idle || !r->pending || !r->sums || (count_visits && !r->visits))
        ex_die(prog, "out of memory for %u paths in flight and %zu pixels", n, pixels);
    for (i = 0; i < n; i++) r->idle[i] = n - 1 - i;
    r->idle_count = n;
}

static void renderer_free(renderer *r)
{
    free(r->paths);
    free(r->idle);
    free(r->pending);
    free(r->sums);
    free(r->visits);
}

/* Path number `number` starts with a camera ray jittered in its pixel. */
static void start_path(const render_job *job, uint64_t number, path_state *p)
{
    uint64_t pixels = (uint64_t)job->camera.width * job->camera.height;
    uint32_t px;
    p->pixel = (uint32_t)(number % pixels);
    p->sample = (uint32_t)(number / pixels);
    p->bounce = 0;
    p->weight[0] = p->weight[1] = p->weight[2] = 1.0;
    p->in_shadow_step = 0;
    p->luminance = 0.0;
    px = p->pixel % job->camera.width;
    ex_camera_ray(&job->camera,
                  (px + random_at(p->pixel, p->sample, 0, DIM_PIXEL_X)) / job->camera.width,
                  (p->pixel / job->camera.width + random_at(p->pixel, p->sample, 0, DIM_PIXEL_Y))
                      / job->camera.height,
                  &p->ray);
}

/* brt_ray_source.next_rays: bounce rays first (their paths are already
** started), then new paths while there are idle slots. */
static size_t next_rays(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    renderer *r = user;
    size_t n = 0;
    if (ex_interrupted()) return 0;   /* the paths in flight end; main exits */
    while (n < max && r->pending_count > 0) {
        uint32_t id = r->pending[--r->pending_count];
        const path_state *p = &r->paths[id];
        rays[n] = p->in_shadow_step ? p->shadow : p->ray;
        tags[n++] = id | (p->in_shadow_step ? BRT_TAG_OCCLUSION : 0);
    }
    while (n < max && r->idle_count > 0 && r->started < r->total) {
        uint32_t id = r->idle[--r->idle_count];
        start_path(r->job, r->started++, &r->paths[id]);
        rays[n] = r->paths[id].ray;
        tags[n++] = id;
    }
    return n;
}

/* Adds weight * radiance (per channel) to the path's pixel, in fixed point. */
static void add_radiance(renderer *r, path_state *p, const double weight[3], const double radiance[3])
{
    int k;
    for (k = 0; k < 3; k++) {
        double v = fmin(weight[k] * radiance[k], SAMPLE_CLAMP);
        r->sums[3 * (size_t)p->pixel + k] += (uint64_t)(v * FIXED_ONE + 0.5);
        p->luminance += v / 3.0;
    }
}

/* What an escaping ray sees: the sky, and the sun only without shadow
** rays (with them, the sun comes through the shadow rays alone). */
static void escape_radiance(const render_job *job, const float d[3], double rgb[3])
{
    int k;
    sky_radiance(d, rgb);
    if (!job->nee && sees_sun(&job->sun, d))
        for (k = 0; k < 3; k++) rgb[k] += job->sun.radiance[k];
}

/* Next-event estimation at the hit of ray: the shadow ray toward a point
** of the sun's disc and, in p->light, what it adds when clear: the Lambert
** BRDF albedo / pi times the sun's radiance, cos, and 1 / pdf = the disc's
** solid angle; p->weight already holds the albedo.  Returns 0 when the
** sun is behind the surface (nothing to add, no ray). */
static int sun_sample(const render_job *job, path_state *p, const brt_ray *ray,
                      const brt_hit *hit, const float normal[3])
{
    double n[3], org[3], point[3], cosine;
    int k;
    for (k = 0; k < 3; k++) {
        n[k] = normal[k];
        point[k] = (double)ray->org[k] + (double)hit->t * ray->dir[k];
    }
    if (!ex_surface_point(point, n, ray->dir, job->diagonal, n, org)) return 0;
    ex_cone_ray(org, job->sun.dir, job->sun.cos_max,
                random_at(p->pixel, p->sample, p->bounce, DIM_SUN_Z),
                random_at(p->pixel, p->sample, p->bounce, DIM_SUN_PHI), &p->shadow);
    cosine = n[0] * p->shadow.dir[0] + n[1] * p->shadow.dir[1] + n[2] * p->shadow.dir[2];
    if (!(cosine > 0)) return 0;
    for (k = 0; k < 3; k++)
        p->light[k] = p->weight[k] / PI * job->sun.radiance[k] * cosine * job->sun.solid_angle;
    return 1;
}

/* One more hit: absorb, end by depth, sample the sun (p->in_shadow_step),
** end by roulette, or bounce.  Returns 1 when the path goes on with
** p->ray. */
static int scatter(const render_job *job, path_state *p, const brt_ray *ray, const brt_hit *hit,
                   const float normal[3])
{
    float albedo[3] = {ALBEDO, ALBEDO, ALBEDO};
    int k;
    p->bounce++;
    if (p->bounce >= MAX_DEPTH) return 0;
    if (job->palette) ex_instanced_colour(job->palette, hit->inst, hit->prim, albedo);
    for (k = 0; k < 3; k++) p->weight[k] *= albedo[k];   /* Lambert, cosine sampled: f cos / pdf = albedo */
    /* Before the roulette: the shadow ray stands for the bounce ray that
    ** would find the sun, whose weight the roulette only rescales. */
    p->in_shadow_step = job->nee && sun_sample(job, p, ray, hit, normal);
    if (p->bounce >= ROULETTE_DEPTH) {
        double survive = fmin(0.95, fmax(p->weight[0], fmax(p->weight[1], p->weight[2])));
        if (random_at(p->pixel, p->sample, p->bounce, DIM_ROULETTE) >= survive) return 0;
        for (k = 0; k < 3; k++) p->weight[k] /= survive;
    }
    return lambert_bounce(ray, hit, normal, job->diagonal,
                          random_at(p->pixel, p->sample, p->bounce, DIM_DIRECTION_R),
                          random_at(p->pixel, p->sample, p->bounce, DIM_DIRECTION_PHI), &p->ray);
}

/* brt_ray_source.finished: a shadow ray adds the sun when clear; a path
** ray escapes to the sky, or hits.  The path then ends or waits with its
** next ray (the shadow ray first, when there is one) for next_rays. */
static void finished(void *user, const brt_ray *ray, const brt_hit *hit, const float normal[3],
                     uint32_t visits, uint64_t tag)
{
    renderer *r = user;
    uint32_t id = (uint32_t)(tag & ~BRT_TAG_OCCLUSION);
    path_state *p = &r->paths[id];
    int goes_on;
    if (r->visits) r->visits[p->pixel] += visits;
    if (tag & BRT_TAG_OCCLUSION) {
        static const double one[3] = {1.0, 1.0, 1.0};
        if (hit->prim == BRT_NO_PRIM) add_radiance(r, p, one, p->light);
        p->in_shadow_step = 0;
        goes_on = p->goes_on;
    } else if (hit->prim == BRT_NO_PRIM) {
        double sky[3];
        escape_radiance(r->job, ray->dir, sky);
        add_radiance(r, p, p->weight, sky);
        goes_on = 0;
    } else {
        p->goes_on = goes_on = scatter(r->job, p, ray, hit, normal);
        goes_on |= p->in_shadow_step;
    }
    if (goes_on) {
        r->pending[r->pending_count++] = id;
        return;
    }
    r->idle[r->idle_count++] = id;
    r->moments.sum += p->luminance;
    r->moments.sum_sq += p->luminance * p->luminance;
    r->moments.count++;
    r->finished++;
    if ((r->finished & 0xFFF) == 0) ex_progress("rendering", r->finished, r->total);
}

/* The progress line at 100 % and done; after SIGINT or SIGTERM (the
** paths stopped early), the exit, before any output is written. */
static void end_progress(const renderer *r)
{
    if (ex_interrupted()) ex_die_interrupted(prog);
    ex_progress("rendering", r->total, r->total);
    ex_progress_end();
}

/* ===================================================================== */
/* The two tracers                                                       */
/* ===================================================================== */

/* --direct's scene in memory: a mesh's BVH, or the world of an instanced
** scene (brt_world: its prototypes' BVHs under the instances). */
typedef struct direct_scene {
    brt_bvh *bvh;
    brt_world *world;
    double build_seconds;
} direct_scene;

/* The reference: the same paths against the scene in memory. */
static void render_direct(const direct_scene *d, renderer *r, brt_stats *stats)
{
    static brt_ray rays[DIRECT_CHUNK];
    static uint64_t tags[DIRECT_CHUNK];
    static brt_hit hits[DIRECT_CHUNK];
    static float normals[3 * DIRECT_CHUNK];
    double start = brt_seconds();
    size_t n, i;
    while ((n = next_rays(r, rays, tags, DIRECT_CHUNK)) > 0) {
        if (d->world) brt_world_trace(d->world, rays, tags, n, hits, normals, r->job->threads);
        else brt_bvh_trace(d->bvh, rays, tags, n, hits, normals, r->job->threads);
        for (i = 0; i < n; i++) {
            int shadow = (tags[i] & BRT_TAG_OCCLUSION) != 0;
            stats->occlusion_rays += shadow;
            stats->occlusion_hits += shadow && hits[i].prim != BRT_NO_PRIM;
            finished(r, &rays[i], &hits[i], normals + 3 * i, 0, tags[i]);
        }
        stats->rays += n;
    }
    stats->seconds = brt_seconds() - start;
}

static void render_batched(brt_scene *scene, const brt_trace_options *topt, renderer *r,
                           brt_stats *stats)
{
    brt_ray_source source;
    brt_error err;
    brt_result res;
    source.next_rays = next_rays;
    source.finished = finished;
    source.user = r;
    res = brt_scene_trace_stream(scene, topt, &source, stats, &err);
    ex_check(prog, res, &err);   /* BRT_EINTR between batches (topt->interrupt): the signal's exit */
}

/* ---- end of the integrator ---- */

/* ===================================================================== */
/* The scene                                                             */
/* ===================================================================== */

/* What render reads: a built-in instanced scene (landscape, island), a
** pbrt file (both as a brt_scene_source), or a mesh: the built-in crown
** or a mesh file. */
typedef struct render_input {
    ex_instanced_scene *instanced;
    ex_input file;                  /* a mesh or pbrt file named on the command line */
    const brt_scene_source *source; /* instanced or pbrt, else NULL */
    brt_scene_source streams;
} render_input;

static int is_instanced_builtin(const char *name)
{
    return strcmp(name, "landscape") == 0 || strcmp(name, "island") == 0;
}

static void open_input(const options *o, render_input *in)
{
    brt_error err;
    memset(in, 0, sizeof *in);
    if (is_instanced_builtin(o->input)) {
        ex_check(prog, ex_instanced_open(o->input, o->scale, o->seed, &in->instanced, &err), &err);
        ex_instanced_source(in->instanced, &in->streams);
        in->source = &in->streams;
    } else if (!ex_scene_is_builtin(o->input)) {
        ex_input_open(prog, o->input, &in->file);
        if (in->file.pbrt) in->source = &in->file.source;
    }
}

/* The default --point-tris (ex_default_point_tris, trace's rule) from the
** scene's unique triangles before any build: an instanced built-in
** scene's from its open recipe, the crown's counted without its geometry
** (ex_scene_count), a file's as trace counts it (ex_input_triangles). */
static void point_size(options *o, const render_input *in)
{
    uint64_t triangles = 0, vertices;
    brt_error err;
    if (o->point_tris) return;
    if (in->instanced) {
        triangles = ex_instanced_unique(in->instanced);
    } else if (ex_scene_is_builtin(o->input)) {
        ex_scene_recipe recipe;
        recipe.name = o->input;
        recipe.scale = o->scale;
        recipe.seed = o->seed;
        ex_check(prog, ex_scene_count(&recipe, &vertices, &triangles, &err), &err);
    } else {
        triangles = ex_input_triangles(&in->file);
    }
    o->point_tris = ex_default_point_tris(triangles, o->memory, o->memory_percent);
}

static void close_input(render_input *in)
{
    ex_instanced_close(in->instanced);
    ex_input_close(&in->file);
}

/* The whole scene in memory: only --direct and the direct run of --compare
** need it (a mesh says so when it is larger than the memory limit);
** *triangles: the unique ones. */
static void load_direct(const options *o, const render_input *in, uint64_t limit, direct_scene *d,
                        float bmin[3], float bmax[3], uint64_t *triangles)
{
    brt_mesh mesh;
    brt_error err;
    double start = brt_seconds();
    memset(d, 0, sizeof *d);
    if (in->source) {
        ex_check(prog, brt_world_build(in->source, &d->world, &err), &err);
        brt_world_bounds(d->world, bmin, bmax);
        *triangles = brt_world_unique_triangles(d->world);
        d->build_seconds = brt_seconds() - start;
        return;
    }
    if (ex_scene_is_builtin(o->input))
        ex_check(prog, ex_scene_generate(o->input, o->scale, o->seed, &mesh, &err), &err);
    else
        ex_check(prog, brt_mesh_load(o->input, &mesh, &err), &err);
    ex_note_mesh_memory(prog, &mesh, limit);
    ex_check(prog, brt_bvh_build(mesh.positions, mesh.indices, mesh.triangle_count, NULL, &d->bvh),
             NULL);
    brt_mesh_bounds(&mesh, bmin, bmax);
    *triangles = mesh.triangle_count;
    brt_mesh_free(&mesh);
    d->build_seconds = brt_seconds() - start;
}

static void free_direct(direct_scene *d)
{
    brt_bvh_free(d->bvh);
    brt_world_free(d->world);
}

/* The sun of --sun, --sun-radius and --sun-radiance: a warm white disc.
** By default low (20 degrees) and to the side of the default view, so that
** shadows fall long and across the picture: for the landscape from the
** right and a little behind its trees and rocks; for the island from
** behind the camera's left, so the islands' shadows fall on the sea beside
** them; for the crown and meshes high from the front right, the old sky's
** sun lobe. */
static void make_sun(const options *o, sun_light *sun)
{
    static const double colour[3] = {1.0, 0.92, 0.78};
    static const double landscape[3] = {0.75, 0.35, 0.1}, island[3] = {0.6, 0.3, -0.75};
    static const double other[3] = {0.48, 0.62, 0.62};
    const double *fallback = strcmp(o->input, "landscape") == 0 ? landscape
                             : strcmp(o->input, "island") == 0 ? island : other;
    double len = 0;
    int k;
    for (k = 0; k < 3; k++) {
        sun->dir[k] = o->have_sun ? o->sun[k] : fallback[k];
        len += sun->dir[k] * sun->dir[k];
    }
    for (k = 0; k < 3; k++) {
        sun->dir[k] /= sqrt(len);
        sun->radiance[k] = o->sun_radiance * colour[k];
    }
    sun->cos_max = cos(o->sun_radius * PI / 180.0);
    sun->solid_angle = 2.0 * PI * (1.0 - sun->cos_max);
}

/* The camera (given, a pbrt file's, or the scene's default view) and the offset scale,
** from the scene's bounds: the mesh's (--direct) or the scene file's,
** which are the same floats (README: "Out of core from end to end"). */
static void make_job(const options *o, const render_input *in, const float bmin[3],
                     const float bmax[3], render_job *job)
{
    float eye[3], target[3], fov;
    ex_camera *cam = &job->camera;
    if (o->have_camera) {
        memcpy(eye, o->eye, sizeof eye);
        memcpy(target, o->target, sizeof target);
        fov = o->fov;
        ex_camera_look(cam, eye, target, fov, (uint32_t)o->width, (uint32_t)o->height);
    } else if (in->file.pbrt && ex_pbrt_camera_frame(in->file.pbrt, (uint32_t)o->width, (uint32_t)o->height,
                                                     cam->eye, cam->forward, cam->right, cam->up)) {
        /* pbrt-v4's camera as it defines it: handedness, up vector, fov
        ** across the shorter side, screen window (examples/lib/pbrt.h). */
        cam->width = (uint32_t)o->width;
        cam->height = (uint32_t)o->height;
    } else {
        ex_scene_camera(o->input, bmin, bmax, eye, target, &fov);
        ex_camera_look(cam, eye, target, fov, (uint32_t)o->width, (uint32_t)o->height);
    }
    job->spp = (uint32_t)o->spp;
    job->diagonal = ex_box_diagonal(bmin, bmax);
    job->paths_in_flight = (uint32_t)o->rays_in_flight;
    job->threads = (unsigned)o->threads;
    job->disk_speed = o->disk_speed;
    make_sun(o, &job->sun);
    job->sun_radius = o->sun_radius;
    job->nee = !o->no_nee;
}

/* DIR/NAME-sSCALE-seedSEED-bBATCH-iINSTANCED-rRES.brs in the scene folder
** (ex_scene_folder). */
static void builtin_scene_path(const options *o, char *path, size_t size)
{
    char dir[4096];
    ex_scene_folder(prog, dir, sizeof dir);
    if (snprintf(path, size, "%s/%s-s%g-seed%llu-b%llu-i%llu-r%llu.brs", dir, o->input, o->scale,
                 (unsigned long long)o->seed, (unsigned long long)o->point_tris,
                 (unsigned long long)o->point_instanced, (unsigned long long)o->res) >= (int)size)
        ex_die(prog, "%s: scene path too long", dir);
}

/* A default scene path for --exact-voxels, NAME-exact-voxels.brs:
** the analysis's proxies get their own file, so that runs with and without
** it reuse theirs instead of rebuilding each other's. */
static void exact_voxels_path(char *path, size_t size)
{
    const size_t n = strlen(path) - strlen(".brs");
    if (snprintf(path + n, size - n, "-exact-voxels.brs") >= (int)(size - n))
        ex_die(prog, "%s: scene path too long", path);
}

/* The scene file at path, opened when it was built from stamp with sopt
** (brt_scene_matches); otherwise built from source with
** brt_scene_build_source and opened.  A file there that does not open
** (corrupt, another format version) is an error, as in brt_scene_prepare,
** unless replace_unreadable (render's own cache of built-in scenes). */
static brt_scene *prepare_scene(const brt_scene_source *source, uint64_t stamp,
                                const char *path, const brt_scene_options *sopt,
                                int replace_unreadable, int *rebuilt)
{
    brt_scene *scene = NULL;
    brt_error err;
    brt_result r;
    struct stat st;
    *rebuilt = 0;
    if (stat(path, &st) == 0) {
        r = brt_scene_open(path, &scene, &err);
        if (r == BRT_OK && brt_scene_matches(scene, stamp, sopt)) return scene;
        if (r != BRT_OK && !replace_unreadable) ex_check(prog, r, &err);
        brt_scene_close(scene);   /* stale: the source or the settings changed */
    }
    *rebuilt = 1;
    ex_progress("building scene", 0, 1);
    ex_check(prog, brt_scene_build_source(source, sopt, stamp, path, &err), &err);
    ex_progress("building scene", 1, 1);
    ex_progress_end();
    ex_check(prog, brt_scene_open(path, &scene, &err), &err);
    return scene;
}

/* The scene file: reused when it matches the input (a mesh file's stamp,
** or a built-in scene's recipe), else built from a triangle stream -- the
** mesh file read, or the built-in scene made, as the build consumes it. */
static brt_scene *open_scene(const options *o, const render_input *in,
                             const volatile sig_atomic_t *interrupt, double *build_seconds)
{
    brt_scene_options sopt;
    brt_scene_source source;
    ex_scene_recipe recipe;
    brt_scene *scene;
    brt_error err;
    char path[4096];
    double start = brt_seconds();
    uint64_t stamp;
    int builtin = ex_scene_is_builtin(o->input), rebuilt;
    memset(&sopt, 0, sizeof sopt);
    sopt.point_tris = (uint32_t)o->point_tris;
    sopt.proxy_res = (uint32_t)o->res;
    sopt.interrupt = interrupt;
    sopt.threads = (unsigned)o->threads;
    sopt.point_instanced = o->point_instanced;
    sopt.exact_voxels = o->exact_voxels;
    if (o->scene) snprintf(path, sizeof path, "%s", o->scene);
    else if (builtin) builtin_scene_path(o, path, sizeof path);
    else ex_default_scene_path(prog, o->input, sopt.point_tris, sopt.proxy_res, path, sizeof path);
    if (!o->scene && o->exact_voxels) exact_voxels_path(path, sizeof path);
    memset(&source, 0, sizeof source);
    if (builtin) {
        recipe.name = o->input;
        recipe.scale = o->scale;
        recipe.seed = o->seed;
        stamp = ex_scene_stamp(&recipe);
        if (in->source) {
            source = *in->source;
            stamp = brt_mix64(stamp ^ 0x696E7374616E6365u);   /* "instance": not the baked scene's */
        } else {
            ex_scene_source(&recipe, &source.world);
        }
    } else {
        if (in->source) source = *in->source;
        else brt_mesh_file_source(o->input, &source.world);
        ex_check(prog, brt_scene_source_stamp(o->input, &stamp, &err), &err);
    }
    /* The folder of built-in scene files is render's own cache: a file
    ** there that does not open is replaced, not reported. */
    scene = prepare_scene(&source, stamp, path, &sopt, builtin, &rebuilt);
    *build_seconds = rebuilt ? brt_seconds() - start : 0.0;
    return scene;
}

/* ===================================================================== */
/* Images                                                                */
/* ===================================================================== */

/* The mean radiance of pixel channel i (3 per pixel, rows top first). */
static double pixel_mean(const render_job *job, const uint64_t *sums, size_t i)
{
    return (double)sums[i] / FIXED_ONE / job->spp;
}

/* Tone mapping of the pixel sums: mean, exposure, Reinhard's x/(1+x),
** gamma 2.2.  Only integer sums go in, so equal sums give equal bytes. */
static unsigned char *tone_map(const render_job *job, const uint64_t *sums)
{
    size_t i, n = 3 * (size_t)job->camera.width * job->camera.height;
    unsigned char *rgb = malloc(n);
    if (!rgb) ex_die(prog, "out of memory for the image");
    for (i = 0; i < n; i++) {
        double v = EXPOSURE * pixel_mean(job, sums, i);
        rgb[i] = (unsigned char)(255.0 * pow(v / (1.0 + v), 1.0 / 2.2) + 0.5);
    }
    return rgb;
}

/* The linear image as a Portable Float Map: "PF", width, height, -1 (little
** endian), then float RGB rows from the bottom row up. */
/* A run writes up to four files one after another (PNG, heat map, PFM,
** statistics); when a later one fails, ex_check exits 1 and the earlier
** ones must go too (README, "Errors": a failed program leaves no output
** file).  Each file written is noted; at exit, unless main finished, the
** regular ones are removed (never a device such as /dev/null). */
static const char *written[16];
static int written_count, render_finished;

static void remove_written(void)
{
    struct stat st;
    int i;
    if (render_finished) return;
    for (i = 0; i < written_count; i++)
        if (stat(written[i], &st) == 0 && S_ISREG(st.st_mode)) unlink(written[i]);
}

static void note_written(const char *path)
{
    static char copies[16][4096];
    if (written_count < 16 && snprintf(copies[written_count], sizeof copies[0], "%s", path) < (int)sizeof copies[0])
        written[written_count] = copies[written_count], written_count++;
}

static void write_pfm(const char *path, const render_job *job, const uint64_t *sums)
{
    size_t w = job->camera.width, h = job->camera.height, x, y, k, at;
    char header[64];
    int head = snprintf(header, sizeof header, "PF\n%u %u\n-1.0\n", job->camera.width,
                        job->camera.height);
    unsigned char *data = malloc((size_t)head + 12 * w * h);
    brt_error err;
    if (!data) ex_die(prog, "out of memory for %s", path);
    memcpy(data, header, (size_t)head);
    at = (size_t)head;
    for (y = h; y-- > 0;)
        for (x = 0; x < w; x++)
            for (k = 0; k < 3; k++, at += 4) {
                float v = (float)pixel_mean(job, sums, 3 * (y * w + x) + k);
                uint32_t bits;
                memcpy(&bits, &v, 4);
                brt_put_le32(data + at, bits);
            }
    ex_check(prog, brt_write_file_atomic(path, data, at, &err), &err);
    note_written(path);
    free(data);
}

/* The root mean square difference, over every pixel channel, between this
** image's mean radiance and a --pfm written by an earlier render of the
** same size. */
static double rmse_against(const char *path, const render_job *job, const uint64_t *sums)
{
    FILE *f = fopen(path, "rb");
    unsigned w = 0, h = 0;
    double scale = 0, sum = 0;
    size_t x, y, k;
    if (!f) ex_die(prog, "%s: cannot open: %s", path, strerror(errno));
    if (fscanf(f, "PF %u %u %lf", &w, &h, &scale) != 3 || fgetc(f) != '\n' || scale >= 0)
        ex_die(prog, "%s: not a little-endian colour PFM", path);
    if (w != job->camera.width || h != job->camera.height)
        ex_die(prog, "%s: %ux%u, but this image is %ux%u", path, w, h, job->camera.width,
               job->camera.height);
    for (y = h; y-- > 0;)
        for (x = 0; x < w; x++)
            for (k = 0; k < 3; k++) {
                unsigned char b[4];
                uint32_t bits;
                float v;
                double d;
                if (fread(b, 1, 4, f) != 4) ex_die(prog, "%s: truncated", path);
                bits = brt_get_le32(b);
                memcpy(&v, &bits, 4);
                d = pixel_mean(job, sums, 3 * (y * w + x) + k) - v;
                sum += d * d;
            }
    fclose(f);
    return sqrt(sum / (3.0 * w * h));
}

/* The heat map of visits per sample (report.h), noted as written. */
static void write_heatmap(const char *path, const render_job *job, const uint64_t *visits,
                          double max)
{
    brt_error err;
    ex_check(prog, ex_heatmap_write(prog, path, job->camera.width, job->camera.height, visits,
                                    job->spp, max, &err), &err);
    note_written(path);
}

/* The top of the heat map's colour scale (ex_heat_scale). */
static double heat_scale(const render_job *job, const uint64_t *visits)
{
    return ex_heat_scale(prog, visits, (size_t)job->camera.width * job->camera.height, job->spp);
}

/* ===================================================================== */
/* Runs, statistics and the comparison table                             */
/* ===================================================================== */

/* One render's outcome. */
typedef struct run {
    const char *label;
    brt_stats stats;
    uint64_t *sums;            /* pixel sums (owned) */
    uint64_t *visits;          /* batching points visited per pixel, or NULL (owned) */
    uint64_t heat_visits;      /* their total */
    sample_moments moments;
    double rmse;               /* against --reference; NAN without one */
} run;

static void run_batched(brt_scene *scene, const render_job *job, const brt_trace_options *topt,
                        int heatmap, run *out)
{
    renderer r;
    size_t pixels = (size_t)job->camera.width * job->camera.height, i;
    renderer_init(&r, job, heatmap);
    render_batched(scene, topt, &r, &out->stats);
    out->stats.build_seconds = job->scene_seconds;
    end_progress(&r);
    out->sums = r.sums;
    out->visits = r.visits;
    out->moments = r.moments;
    for (i = 0; r.visits && i < pixels; i++) out->heat_visits += r.visits[i];
    r.sums = NULL;
    r.visits = NULL;
    renderer_free(&r);
}

static void run_direct(const direct_scene *d, const render_job *job, run *out)
{
    renderer r;
    out->stats.build_seconds = d->build_seconds;
    renderer_init(&r, job, 0);
    render_direct(d, &r, &out->stats);
    end_progress(&r);
    if (out->stats.seconds > 0) out->stats.mrays_per_second = out->stats.rays / out->stats.seconds * 1e-6;
    out->sums = r.sums;
    out->moments = r.moments;
    r.sums = NULL;
    renderer_free(&r);
}

static double visits_per_sample(const render_job *job, const brt_stats *s)
{
    return (double)s->visits / ((double)job->camera.width * job->camera.height * job->spp);
}

/* The library's statistics plus the renderer's, as one JSON object: the
** library writes its object, and the renderer's fields go before its "}". */
static void write_stats(const char *path, const render_job *job, const run *x, int direct,
                        int proxies)
{
    char extra[2048];
    brt_error err;
    const sample_moments *m = &x->moments;
    double n = m->count > 1 ? (double)m->count : 2.0, mean = m->sum / n;
    /* The standard error of the mean: the samples are independent (each
    ** draws its own random numbers), so it is their sd / sqrt(n). */
    double se = sqrt(fmax(0.0, m->sum_sq / n - mean * mean) / (n - 1.0));
    char rmse[64];
    if (isnan(x->rmse)) snprintf(rmse, sizeof rmse, "null");
    else snprintf(rmse, sizeof rmse, "%.17g", x->rmse);
    snprintf(extra, sizeof extra,
             "  \"mode\": \"%s\",\n  \"proxies\": %d,\n  \"width\": %u,\n  \"height\": %u,\n"
             "  \"spp\": %u,\n  \"max_depth\": %d,\n  \"paths\": %llu,\n"
             "  \"paths_in_flight\": %u,\n  \"visits_per_sample\": %.17g,\n"
             "  \"heatmap_visits\": %llu,\n  \"disk_speed\": %llu,\n  \"nee\": %d,\n"
             "  \"sun_radius_degrees\": %.17g,\n  \"sun_radiance\": %.17g,\n"
             "  \"mean_luminance\": %.17g,\n  \"mean_luminance_se\": %.17g,\n  \"rmse\": %s",
             direct ? "direct" : "batched", proxies, job->camera.width, job->camera.height, job->spp,
             MAX_DEPTH, (unsigned long long)job->camera.width * job->camera.height * job->spp,
             job->paths_in_flight, visits_per_sample(job, &x->stats),
             (unsigned long long)x->heat_visits, (unsigned long long)job->disk_speed, job->nee,
             job->sun_radius, job->sun.radiance[0], mean, se, rmse);
    ex_check(prog, ex_stats_write(path, &x->stats, extra, &err), &err);
    note_written(path);
}

/* "x.png" -> "x-suffix.png". */
static void suffixed(const char *path, const char *suffix, char *out, size_t size)
{
    const char *dot = strrchr(path, '.'), *slash = strrchr(path, '/');
    int stem = dot && (!slash || dot > slash) ? (int)(dot - path) : (int)strlen(path);
    snprintf(out, size, "%.*s-%s%s", stem, path, suffix, path + stem);
}

static void free_run(run *x)
{
    free(x->sums);
    free(x->visits);
}

/* ===================================================================== */
/* main                                                                  */
/* ===================================================================== */

/* The PNG, and the linear image and its RMSE when asked for. */
static void write_image(const options *o, const render_job *job, run *x)
{
    unsigned char *rgb = tone_map(job, x->sums);
    brt_error err;
    if (o->pfm) write_pfm(o->pfm, job, x->sums);
    if (o->reference) {
        x->rmse = rmse_against(o->reference, job, x->sums);
        printf("RMSE against %s: %.6g\n", o->reference, x->rmse);
    }
    ex_check(prog, ex_png_write_rgb(o->out, (int)job->camera.width, (int)job->camera.height, rgb,
                                    &err), &err);
    note_written(o->out);
    free(rgb);
}

static void describe(const options *o, uint64_t triangles, brt_scene *scene, uint64_t limit)
{
    if (scene && brt_scene_prototype_count(scene))
        printf("%s: %llu unique (%llu in prototypes), %llu instanced triangles, %u instances",
               o->input, (unsigned long long)brt_scene_unique_triangles(scene),
               (unsigned long long)(brt_scene_unique_triangles(scene) - brt_scene_triangle_count(scene)),
               (unsigned long long)brt_scene_instanced_triangles(scene), brt_scene_instance_count(scene));
    else
        printf("%s: %llu triangles", o->input, (unsigned long long)triangles);
    if (scene) {
        printf(", %u batching points of <= %llu, proxies %llu^3, ", brt_scene_point_count(scene),
               (unsigned long long)o->point_tris, (unsigned long long)o->res);
        if (limit) printf("memory limit %.1f MiB", limit / 1048576.0);
        else printf("no memory limit");
    }
    printf("; %llux%llu, %llu spp\n", (unsigned long long)o->width, (unsigned long long)o->height,
           (unsigned long long)o->spp);
}

/* --compare: batched without and with proxies at the same limit, and the
** direct reference; one table, the image, the two heatmaps. */
static void compare(const options *o, const render_input *in, const render_job *job,
                    brt_scene *scene, const brt_trace_options *topt)
{
    run runs[3];
    brt_trace_options without = *topt, with = *topt;
    size_t pixels = (size_t)job->camera.width * job->camera.height;
    char path[4096];
    double max;
    int i;
    memset(runs, 0, sizeof runs);
    for (i = 0; i < 3; i++) runs[i].rmse = NAN;
    runs[0].label = "direct (in memory)";
    runs[1].label = "batched, no proxies";
    runs[2].label = with.exact_proxies ? "batched, exact proxies" : "batched, proxies";
    without.no_proxy = 1;
    with.no_proxy = 0;
    {
        direct_scene d;
        float bmin[3], bmax[3];
        uint64_t triangles;
        load_direct(o, in, topt->memory_limit, &d, bmin, bmax, &triangles);
        run_direct(&d, job, &runs[0]);
        free_direct(&d);
    }
    run_batched(scene, job, &without, o->heatmap != NULL, &runs[1]);
    run_batched(scene, job, &with, o->heatmap != NULL, &runs[2]);
    ex_compare_header();
    for (i = 0; i < 3; i++)
        ex_compare_row(runs[i].label, &runs[i].stats, visits_per_sample(job, &runs[i].stats),
                       memcmp(runs[i].sums, runs[0].sums, 3 * pixels * sizeof *runs[0].sums) == 0);
    ex_compare_ratios(&runs[1].stats, &runs[2].stats);
    write_image(o, job, &runs[2]);
    if (o->heatmap) {
        /* One colour scale for both, so that they can be compared. */
        max = o->heat_max > 0 ? o->heat_max : fmax(heat_scale(job, runs[1].visits),
                                                   heat_scale(job, runs[2].visits));
        suffixed(o->heatmap, "noproxy", path, sizeof path);
        write_heatmap(path, job, runs[1].visits, max);
        suffixed(o->heatmap, "proxy", path, sizeof path);
        write_heatmap(path, job, runs[2].visits, max);
    }
    if (o->stats) {
        runs[1].stats.peak_rss_bytes = runs[2].stats.peak_rss_bytes = brt_peak_rss_bytes();
        write_stats(o->stats, job, &runs[2], 0, 1);
        suffixed(o->stats, "noproxy", path, sizeof path);
        write_stats(path, job, &runs[1], 0, 0);
    }
    for (i = 0; i < 3; i++) free_run(&runs[i]);
}

static void render_once(const options *o, const direct_scene *d, const render_job *job,
                        brt_scene *scene, const brt_trace_options *topt)
{
    run x;
    memset(&x, 0, sizeof x);
    x.rmse = NAN;
    if (o->direct) run_direct(d, job, &x);
    else run_batched(scene, job, topt, o->heatmap != NULL, &x);
    x.stats.peak_rss_bytes = brt_peak_rss_bytes();
    printf("%s: %.2f s, %.3f Mrays/s, %llu rays; read %.2f MiB in %llu loads (%.2f s); "
           "%.2f batching points visited per sample; peak RSS %.1f MiB\n",
           o->direct ? "direct" : "batched", x.stats.seconds, x.stats.mrays_per_second,
           (unsigned long long)x.stats.rays, x.stats.disk_bytes_read / 1048576.0,
           (unsigned long long)x.stats.batch_loads, x.stats.load_seconds,
           visits_per_sample(job, &x.stats), x.stats.peak_rss_bytes / 1048576.0);
    write_image(o, job, &x);
    if (o->heatmap)
        write_heatmap(o->heatmap, job, x.visits,
                      o->heat_max > 0 ? o->heat_max : heat_scale(job, x.visits));
    if (o->stats) write_stats(o->stats, job, &x, o->direct, !o->direct && !o->no_proxy);
    free_run(&x);
}

int main(int argc, char **argv)
{
    options o;
    render_input in;
    direct_scene direct;
    brt_scene *scene = NULL;
    brt_trace_options topt;
    render_job job;
    const volatile sig_atomic_t *interrupt;
    float bmin[3], bmax[3];
    uint64_t triangles;

    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    atexit(remove_written);
    parse_options(argc, argv, &o);
    interrupt = ex_catch_interrupts();
    memset(&job, 0, sizeof job);
    memset(&topt, 0, sizeof topt);
    open_input(&o, &in);
    if (in.file.pbrt) {   /* a pbrt file's image is its Film's unless given */
        uint32_t fw, fh;
        float e[3], t[3], u[3], f;
        /* pbrt's 1280x720 default when the file has a camera but no Film; a
        ** file with neither (geometry alone) keeps render's default view */
        int film = ex_pbrt_film(in.file.pbrt, &fw, &fh) || ex_pbrt_camera(in.file.pbrt, e, t, u, &f, NULL);
        if (!film) fw = (uint32_t)o.width, fh = (uint32_t)o.height;
        if (!o.have_width) o.width = fw;
        if (!o.have_height) o.height = fh;
        if (o.width > 16384 || o.height > 16384)
            ex_die(prog, "%s: Film of %llux%llu pixels, beyond 16384 a side: give --width and --height",
                   o.input, (unsigned long long)o.width, (unsigned long long)o.height);
    }
    topt.no_proxy = o.no_proxy;
    topt.no_inner = o.no_inner;
    topt.paper_scheduler = o.paper_scheduler;
    topt.no_clip = o.no_clip;
    topt.no_order = o.no_order;
    topt.proxies_in_core = o.proxies_in_core;
    topt.exact_proxies = o.exact_proxy;
    topt.rays_in_flight = (uint32_t)o.rays_in_flight;
    topt.threads = (unsigned)o.threads;
    topt.drop_os_cache = o.drop_os_cache;
    topt.interrupt = interrupt;
    if (o.disk_speed) {
        topt.read_fn = ex_slow_disk_read;
        topt.read_user = &o.disk_speed;
    }
    memset(&direct, 0, sizeof direct);
    if (o.direct) {
        load_direct(&o, &in, o.memory, &direct, bmin, bmax, &triangles);
    } else {
        point_size(&o, &in);
        scene = open_scene(&o, &in, interrupt, &job.scene_seconds);
        brt_scene_bounds(scene, bmin, bmax);
        triangles = brt_scene_triangle_count(scene);
        topt.memory_limit = o.memory_percent > 0
            ? (uint64_t)(o.memory_percent / 100.0 * (double)ex_scene_geometry_bytes(prog, scene)) + 1
            : o.memory;
    }
    make_job(&o, &in, bmin, bmax, &job);
    if (!o.grey) job.palette = in.instanced;
    describe(&o, triangles, scene, topt.memory_limit);
    fflush(stdout);
    if (o.compare) compare(&o, &in, &job, scene, &topt);
    else render_once(&o, &direct, &job, scene, &topt);
    if (scene) brt_scene_close(scene);
    free_direct(&direct);
    close_input(&in);
    render_finished = 1;
    return 0;
}
