/*
** tests/test_render.c -- the renderer (examples/tools/render.c) checked from
** outside, and the SVG plot writer (examples/lib/plot.c) from inside.
**
** The renderer's central promise is determinism (README, "Rendering"): --direct,
** batched with or without proxies, any memory limit and any number of
** rays in flight write byte-identical PNGs.  The tests render a small
** built-in scene and a mesh file under many settings and compare the
** files byte for byte; they also check that paths really bounce (more
** rays than paths), so that identical images are not identically empty.
** Every built-in scene goes through the streamed build (the generator feeds
** brt_scene_build_stream) and must give --direct's image; and a reused
** built-in scene file is rendered without making the scene (peak RSS).
** `figures --only 4` is run on a tiny scene and its table checked for the
** invariants of its runs.
** Programs run from $BRT_BUILD (default build) through system().
*/
#include "test.h"
#include "util.h"
#include "batchrt.h"
#include "../examples/lib/plot.h"
#include "../examples/lib/scenes.h"

#include <dirent.h>
#include <limits.h>
#include <math.h>
#include <stdarg.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>

/* The small scene of these tests: about 5000 triangles in ~17 batching
** points, a tiny image, a few samples. */
#define SMALL "landscape --scale 0.05 --point-tris 300 --width 40 --height 24 --spp 3"

/* ---- running build/render ---- */

/* ---- the tests ---- */

static void test_help(void)
{
    char *out;
    CHECK(tu_run("render --help") == 0, "render --help did not exit 0");
    out = (char *)tu_slurp(tu_scratch("cli.out"), NULL);
    EXPECT(out && strstr(out, "usage: build/render") && strstr(out, "--rays-in-flight"),
           "--help does not print the usage");
    free(out);
    CHECK(tu_run("figures --help") == 0, "figures --help did not exit 0");
    out = (char *)tu_slurp(tu_scratch("cli.out"), NULL);
    EXPECT(out && strstr(out, "usage: build/figures"), "figures --help does not print the usage");
    free(out);
}

/* Settings that change the schedule (and the scene file) but must not
** change one byte of the image. */
static const char *const batched_settings[] = {
    "",                                    /* proxies, no limit, many rays in flight */
    "--no-proxy",
    "--memory 10%",                        /* out of core: reloads */
    "--memory 10% --no-proxy --rays-in-flight 7",
    "--memory 1K --rays-in-flight 1",      /* smaller than any batching point */
    "--rays-in-flight 33 --proxy-res 16",
    "--memory 10% --paper-scheduler",       /* the paper's scheduler */
    "--paper-scheduler",                    /* ... which consults proxies in core too */
    "--memory 10% --disk-speed 1G",        /* reads through render's own reader */
};

static void test_same_image_every_mode(void)
{
    size_t i;
    double rays, paths;
    char *err;
    CHECK(tu_run("render " SMALL " --direct --out @/direct.png --stats @/direct.json") == 0,
          "render --direct failed");
    err = (char *)tu_slurp(tu_scratch("cli.err"), NULL);
    EXPECT(err && err[0] == 0, "stderr is not a terminal, yet render wrote '%s' there", err ? err : "");
    free(err);
    rays = tu_json_file_number(tu_scratch("direct.json"), "rays");
    paths = tu_json_file_number(tu_scratch("direct.json"), "paths");
    CHECK(paths == 40 * 24 * 3 && rays > 1.5 * paths,
          "direct: %g rays for %g paths: the paths do not bounce", rays, paths);
    for (i = 0; i < sizeof batched_settings / sizeof *batched_settings; i++) {
        CHECK(tu_run("render " SMALL " %s --scene @/small-%zu.brs --out @/batched.png --stats @/b.json",
                  batched_settings[i], i) == 0, "render %s failed", batched_settings[i]);
        EXPECT(tu_same_file_bytes(tu_scratch("direct.png"), tu_scratch("batched.png")),
               "'%s': the image differs from --direct", batched_settings[i]);
        EXPECT(tu_json_file_number(tu_scratch("b.json"), "rays") == rays,
               "'%s': %g rays traced, --direct traced %g", batched_settings[i],
               tu_json_file_number(tu_scratch("b.json"), "rays"), rays);
    }
}

/* Shadow rays in every mode: the default (next-event estimation) casts
** them -- the same number and the same answers direct and batched -- and
** --no-nee casts none; both estimators write one image in every mode. */
static void test_nee_same_image_every_mode(void)
{
    static const char *const settings[] = {"--memory 10%", "--memory 1K --no-proxy --rays-in-flight 5",
                                           "--memory 10% --paper-scheduler"};
    static const char *const estimator[] = {"", "--no-nee"};
    double shadow, occluded;
    size_t i, e;
    for (e = 0; e < 2 && !test_failed(); e++) {
        CHECK(tu_run("render " SMALL " %s --direct --out @/nee-direct.png --stats @/nee-direct.json",
                     estimator[e]) == 0, "render --direct %s failed", estimator[e]);
        shadow = tu_json_file_number(tu_scratch("nee-direct.json"), "occlusion_rays");
        occluded = tu_json_file_number(tu_scratch("nee-direct.json"), "occlusion_hits");
        CHECK(e == 1 ? shadow == 0 : shadow > 1000 && occluded > 0 && occluded < shadow,
              "'%s': %g shadow rays, %g occluded", estimator[e], shadow, occluded);
        for (i = 0; i < sizeof settings / sizeof *settings; i++) {
            CHECK(tu_run("render " SMALL " %s %s --scene @/nee.brs --out @/nee.png --stats @/nee.json",
                         estimator[e], settings[i]) == 0, "render %s %s failed", estimator[e], settings[i]);
            EXPECT(tu_same_file_bytes(tu_scratch("nee-direct.png"), tu_scratch("nee.png")),
                   "'%s %s': the image differs from --direct", estimator[e], settings[i]);
            EXPECT(tu_json_file_number(tu_scratch("nee.json"), "occlusion_rays") == shadow &&
                   tu_json_file_number(tu_scratch("nee.json"), "occlusion_hits") == occluded,
                   "'%s %s': %g shadow rays, %g occluded; --direct %g, %g", estimator[e], settings[i],
                   tu_json_file_number(tu_scratch("nee.json"), "occlusion_rays"),
                   tu_json_file_number(tu_scratch("nee.json"), "occlusion_hits"), shadow, occluded);
        }
    }
}

/* Next-event estimation and --no-nee estimate the same image: their means
** over every sample (the renderer's mean_luminance, from the same clamped
** values it adds to the pixels) agree within 4 standard errors of the
** difference, sqrt(se_a^2 + se_b^2), each se the samples' sd / sqrt(n).
** Why 4: the means of 12288 and 196608 independent samples are normal
** to a good approximation, and a correct renderer lands beyond 4 sigma
** with probability 6e-5; the random numbers are a fixed hash of (pixel,
** sample, bounce, dimension), so a given build passes or fails the same
** way every run -- the test cannot be flaky.  A large sun (8 degrees,
** radiance 60, below the sample clamp) keeps --no-nee's variance small
** enough that the sun matters: the image without the sun is checked to
** lie beyond 3 bounds (measured: 0.106 against a bound of 0.020), so that
** a sun counted twice, or left out of either estimator, fails. */
static void test_nee_converges_to_no_nee(void)
{
    const char *scene = "landscape --scale 0.05 --point-tris 300 --width 24 --height 16 "
                        "--sun-radius 8 --scene @/mean.brs";
    double mean[3], se[3], bound;
    const char *const runs[3] = {"--spp 32", "--spp 512 --no-nee", "--spp 32 --sun-radiance 0"};
    int k;
    for (k = 0; k < 3; k++) {
        CHECK(tu_run("render %s --sun-radiance 60 %s --out @/mean.png --stats @/mean.json", scene,
                     runs[k]) == 0, "render %s failed", runs[k]);
        mean[k] = tu_json_file_number(tu_scratch("mean.json"), "mean_luminance");
        se[k] = tu_json_file_number(tu_scratch("mean.json"), "mean_luminance_se");
        CHECK(mean[k] > 0 && se[k] > 0, "%s: mean %g, se %g", runs[k], mean[k], se[k]);
    }
    bound = 4.0 * sqrt(se[0] * se[0] + se[1] * se[1]);
    EXPECT(fabs(mean[0] - mean[1]) <= bound,
           "next-event estimation's mean %.6f and --no-nee's %.6f differ by %.6f > 4 se = %.6f",
           mean[0], mean[1], fabs(mean[0] - mean[1]), bound);
    EXPECT(mean[0] - mean[2] > 3 * bound,
           "the sun adds only %.6f to the mean, not beyond 3x the bound %.6f: the test is blind",
           mean[0] - mean[2], bound);
}

/* --pfm writes the linear image and --reference measures against one: an
** image against its own PFM has an RMSE of float rounding (each mean is
** stored as a float: within 2^-24 of values below 8, so below 1e-6), a noisier
** one of the same view does not, and a PFM of another size is refused. */
static void test_pfm_reference(void)
{
    double same, other;
    CHECK(tu_run("render " SMALL " --direct --pfm @/ref.pfm --out @/ref.png") == 0, "render --pfm failed");
    CHECK(tu_run("render " SMALL " --scene @/pfm.brs --memory 10%% --reference @/ref.pfm "
                 "--out @/p.png --stats @/p.json") == 0, "render --reference failed");
    same = tu_json_file_number(tu_scratch("p.json"), "rmse");
    CHECK(tu_run("render " SMALL " --no-nee --scene @/pfm.brs --reference @/ref.pfm --out @/p.png "
                 "--stats @/p.json") == 0, "render --no-nee --reference failed");
    other = tu_json_file_number(tu_scratch("p.json"), "rmse");
    EXPECT(same < 1e-6 && other > 0.01, "RMSE %g against its own image, %g against --no-nee's", same, other);
    EXPECT(tu_run("render " SMALL " --width 41 --reference @/ref.pfm --out @/never.png") == 1 &&
           !tu_file_exists(tu_scratch("never.png")), "a reference of another size was accepted");
}

/* A mesh file and an explicit camera take the other input path. */
static void test_same_image_mesh_file(void)
{
    const char *camera = "--camera 0.3,1.2,3:0,0.4,0:50 --width 36 --height 20 --spp 2";
    CHECK(tu_run("mkscene crown @/crown.ply --scale 0.05") == 0, "mkscene failed");
    CHECK(tu_run("render @/crown.ply %s --direct --out @/crown-direct.png", camera) == 0,
          "render --direct on a PLY failed");
    CHECK(tu_run("render @/crown.ply %s --point-tris 200 --memory 20%% --scene @/crown.brs "
              "--out @/crown-batched.png", camera) == 0, "render on a PLY failed");
    EXPECT(tu_same_file_bytes(tu_scratch("crown-direct.png"), tu_scratch("crown-batched.png")),
           "crown.ply: batched and direct images differ");
}

/* The heatmap counts every visit of the render exactly once, it
** decodes (an independent decoder, tests/util.c) to the map plus a 24-row
** legend, the map is not flat, and proxies only ever remove visits
** (proxies never change a result; README, "What batchrt promises").  Under a memory limit, so that proxies are
** consulted at all: a culled batching point holds no hit in the ray's
** segment, so every ray reaches the same points with or without proxies,
** and the visits with them plus the culls are exactly the visits without. */
static void test_heatmap(void)
{
    double with, without, culled;
    size_t size = 0, i, distinct = 0;
    int w = 0, h = 0;
    unsigned char *png, *rgb;
    CHECK(tu_run("render " SMALL " --memory 20%% --scene @/heat.brs --heatmap @/heat.png --stats @/heat.json "
              "--out @/img.png") == 0, "render --heatmap failed");
    with = tu_json_file_number(tu_scratch("heat.json"), "heatmap_visits");
    EXPECT(with > 0 && with == tu_json_file_number(tu_scratch("heat.json"), "visits"),
           "heatmap total %g, visits %g", with, tu_json_file_number(tu_scratch("heat.json"), "visits"));
    png = tu_slurp(tu_scratch("heat.png"), &size);
    rgb = png ? tu_png_decode(png, size, &w, &h) : NULL;
    EXPECT(rgb && w == 40 && h == 24 + 24, "heat.png does not decode to 40x48 pixels");
    for (i = 1; rgb && i < (size_t)40 * 24; i++) distinct += memcmp(rgb + 3 * i, rgb, 3) != 0;
    EXPECT(distinct > 0, "the heatmap is one flat colour");
    /* The colour bar (rows 2..9 of the legend under the map) runs from the
    ** scale's bottom colour at its left end to its top colour at its right
    ** end: magma's ends, (0, 0, 4) and (252, 255, 164). */
    if (rgb && w == 40 && h == 48) {
        static const unsigned char bottom[3] = {0, 0, 4}, top[3] = {252, 255, 164};
        const unsigned char *left = rgb + 3 * ((size_t)(24 + 5) * 40), *right = left + 3 * 39;
        EXPECT(memcmp(left, bottom, 3) == 0 && memcmp(right, top, 3) == 0,
               "colour bar ends (%d %d %d) .. (%d %d %d), want (0 0 4) .. (252 255 164)", left[0], left[1],
               left[2], right[0], right[1], right[2]);
    }

    free(rgb);
    free(png);
    CHECK(tu_run("render " SMALL " --memory 20%% --no-proxy --scene @/heat.brs --heatmap @/heat0.png "
              "--stats @/heat0.json --out @/img.png") == 0, "render --no-proxy --heatmap failed");
    without = tu_json_file_number(tu_scratch("heat0.json"), "heatmap_visits");
    culled = tu_json_file_number(tu_scratch("heat.json"), "proxy_culled");
    EXPECT(without == tu_json_file_number(tu_scratch("heat0.json"), "visits") && culled > 0 &&
               with + culled == without,
           "visits: %g with proxies (%g culled), %g without", with, culled, without);
    /* The colour scale's top is the 99.5th percentile of the pixels'
    ** visits per sample: the pixels from sorted index floor(0.995 (n - 1))
    ** up reach it, so at least n minus that index show the top colour (the
    ** colour bar's right end, its row 4).  At 16 samples the top visits
    ** seldom tie, so a scale at the maximum shows fewer. */
    CHECK(tu_run("render landscape --scale 0.05 --point-tris 300 --width 40 --height 24 --spp 16 --memory 20%% "
                 "--scene @/heat.brs --heatmap @/heat16.png --out @/img.png") == 0, "render --spp 16 failed");
    png = tu_slurp(tu_scratch("heat16.png"), &size);
    rgb = png ? tu_png_decode(png, size, &w, &h) : NULL;
    if (rgb && w == 40 && h == 48) {
        size_t n = (size_t)40 * 24, top = 0, at_least = n - (size_t)(0.995 * (double)(n - 1));
        const unsigned char *end = rgb + 3 * ((size_t)(24 + 4) * 40 + 39);
        for (i = 0; i < n; i++) top += memcmp(rgb + 3 * i, end, 3) == 0;
        EXPECT(top >= at_least, "%zu pixels at the colour scale's top, want at least %zu (the 99.5th percentile)",
               top, at_least);
    } else
        EXPECT(0, "heat16.png does not decode to 40x48 pixels");
    free(rgb);
    free(png);
}

static void test_compare(void)
{
    char *out;
    CHECK(tu_run("render " SMALL " --compare --memory 20%% --scene @/cmp.brs --out @/cmp.png "
              "--heatmap @/cmp-heat.png --stats @/cmp.json") == 0, "render --compare failed");
    out = (char *)tu_slurp(tu_scratch("cli.out"), NULL);
    CHECK(out, "no output");
    EXPECT(strstr(out, "| batched, no proxies") && strstr(out, "| batched, proxies")
           && !strstr(out, " NO |"), "--compare table:\n%s", out);
    free(out);
    EXPECT(tu_file_exists(tu_scratch("cmp-heat-noproxy.png")) && tu_file_exists(tu_scratch("cmp-heat-proxy.png"))
           && tu_file_exists(tu_scratch("cmp-noproxy.json")) && tu_file_exists(tu_scratch("cmp.png")),
           "--compare did not write its files");
}

/* --disk-speed: every load lasts at least its bytes / speed, so the
** statistics' loading time is at least the bytes read / speed (a bound the
** reader guarantees by sleeping; nothing here depends on how fast the
** machine is).  Without it the loads of this small scene, all served by
** the OS cache, take far less. */
static void test_disk_speed(void)
{
    const char *json = tu_scratch("disk.json");
    double speed = 32.0 * 1048576, bytes, seconds;
    CHECK(tu_run("render " SMALL " --memory 10%% --disk-speed 32M --scene @/disk.brs "
              "--out @/disk.png --stats @/disk.json") == 0, "render --disk-speed failed");
    bytes = tu_json_file_number(json, "disk_bytes_read");
    seconds = tu_json_file_number(json, "load_seconds");
    CHECK(bytes > 0 && tu_json_file_number(json, "disk_speed") == speed,
          "--disk-speed 32M: %g bytes read, disk_speed %g", bytes, tu_json_file_number(json, "disk_speed"));
    EXPECT(seconds >= bytes / speed && seconds <= tu_json_file_number(json, "seconds"),
           "--disk-speed 32M: %g bytes loaded in %g s (at least %g s expected), trace %g s", bytes,
           seconds, bytes / speed, tu_json_file_number(json, "seconds"));
}

/* Each bad command exits 1 with one line "render: ..." and writes nothing. */
static void test_bad_options(void)
{
    static const char *const bad[] = {
        "--spp 0", "--spp x", "--width -3", "--proxy-res 48", "--memory 0", "--memory 5%x",
        "--camera 1,2,3:1,2,3:40", "--camera 1,2:0,0,0:40", "--camera 0,0,1:0,0,0:180",
        "--bogus", "--direct --heatmap @/never-heat.png", "@/no-such-mesh.obj", "--scale 0",
        "--out", "--disk-speed 0", "--disk-speed fast", "--direct --disk-speed 100M",
        "--sun 0,0,0", "--sun 1,2", "--sun-radius 0", "--sun-radius 90", "--sun-radiance -1",
    };
    char *err = NULL;
    size_t i;
    for (i = 0; i < sizeof bad / sizeof *bad; i++) {
        int status = tu_run(bad[i][0] == '@' ? "render %s --out @/never.png"
                                          : "render " SMALL " --out @/never.png %s", bad[i]);
        err = (char *)tu_slurp(tu_scratch("cli.err"), NULL);
        EXPECT(status == 1, "'%s': exit status %d, expected 1", bad[i], status);
        EXPECT(err && strncmp(err, "render: ", 8) == 0 && strchr(err, '\n') == err + strlen(err) - 1,
               "'%s': expected one line 'render: ...', got '%s'", bad[i], err ? err : "");
        EXPECT(!tu_file_exists(tu_scratch("never.png")) && !tu_file_exists(tu_scratch("never-heat.png")),
               "'%s': an output file was written", bad[i]);
        free(err);
    }
    /* Outputs are renamed over their target: a device or a folder there
    ** is refused up front (a folder stands in for /dev/null, which a
    ** broken guard would replace). */
    EXPECT(tu_run("render " SMALL " --out @") == 1 && (err = (char *)tu_slurp(tu_scratch("cli.err"), NULL)) != NULL
           && strstr(err, "not a regular file"), "--out FOLDER was not refused up front");
    free(err);
}

/* Batched renders of a built-in scene build its scene file from the
** generator's triangle stream, never from a mesh in memory: the image must
** still be --direct's (which does generate the mesh), for every scene, in
** core and out of core. */
static void test_builtin_scenes_streamed(void)
{
    static const char *const scenes[] = {"crown", "landscape", "island"};
    size_t i;
    for (i = 0; i < 3; i++) {
        const char *args = "--scale 0.05 --point-tris 400 --width 32 --height 20 --spp 2";
        CHECK(tu_run("render %s %s --direct --out @/bs-direct.png", scenes[i], args) == 0,
              "render %s --direct failed", scenes[i]);
        CHECK(tu_run("render %s %s --scene @/bs-%s.brs --out @/bs-batched.png", scenes[i], args,
                     scenes[i]) == 0, "render %s failed", scenes[i]);
        EXPECT(tu_same_file_bytes(tu_scratch("bs-direct.png"), tu_scratch("bs-batched.png")),
               "%s: the streamed build's image differs from --direct", scenes[i]);
        CHECK(tu_run("render %s %s --scene @/bs-%s.brs --memory 10%% --out @/bs-batched.png",
                     scenes[i], args, scenes[i]) == 0, "render %s --memory 10%% failed", scenes[i]);
        EXPECT(tu_same_file_bytes(tu_scratch("bs-direct.png"), tu_scratch("bs-batched.png")),
               "%s at 10 %% memory: the image differs from --direct", scenes[i]);
    }
}

/* A reused built-in scene file is rendered from the file alone: the
** scene is not made again (its stamp is the recipe's).  Measured by peak
** RSS against a tiny scene with the same image, paths and cache limit:
** the landscape at scale 5 has 477 thousand unique triangles, 11 MB as an
** indexed mesh (24 bytes a triangle: about one vertex each), and the
** render may exceed the tiny one's peak by at most half of that. */
static void test_reused_builtin_holds_no_mesh(void)
{
    /* --no-nee: no shadow rays, fewer loads (29, not 35), so that glibc's
    ** heap slack from blobs freed and read again (README, "Memory")
    ** stays out of a measure meant for the mesh. */
    const char *args = "--width 16 --height 16 --spp 1 --proxy-res 16 --rays-in-flight 256 --memory 1M "
                       "--no-nee --point-tris 10000";   /* blobs far below the 1M limit */
    uint64_t unique, instanced;
    uint32_t instances;
    double base, peak, mesh_bytes;
    if (!tu_rss_is_meaningful()) return;
    ex_instanced_counts("landscape", 5, &unique, &instanced, &instances);
    mesh_bytes = 24.0 * (double)unique;
    CHECK(tu_run("render crown --scale 0.01 %s --scene @/tiny.brs --out @/tiny.png "
                 "--stats @/tiny.json", args) == 0, "render crown failed");
    base = tu_json_file_number(tu_scratch("tiny.json"), "peak_rss_bytes");
    CHECK(tu_run("render landscape --scale 5 %s --scene @/l5.brs --out @/l5.png", args) == 0,
          "render landscape (build) failed");
    CHECK(tu_run("render landscape --scale 5 %s --scene @/l5.brs --out @/l5.png "
                 "--stats @/l5.json", args) == 0, "render landscape (reuse) failed");
    peak = tu_json_file_number(tu_scratch("l5.json"), "peak_rss_bytes");
    EXPECT(base > 0 && peak > 0 && peak < base + mesh_bytes / 2 &&
           tu_json_file_number(tu_scratch("l5.json"), "build_seconds") == 0,
           "reused scene file: peak RSS %.1f MiB, tiny scene %.1f MiB, the mesh %.1f MiB, "
           "build %g s", peak / 1048576, base / 1048576, mesh_bytes / 1048576,
           tu_json_file_number(tu_scratch("l5.json"), "build_seconds"));
}

/* A built-in scene's file is reused only for the same recipe (README, "The
** scene file": rebuilt when the settings differ): a render of another
** scale or seed into the same --scene file builds it again and gets the
** fresh file's scene, byte for byte the image of a render into a new file. */
static void test_builtin_scene_rebuilt_for_its_recipe(void)
{
    static const char *const changes[] = {"--scale 0.06", "--seed 9"};
    const char *args = "--width 24 --height 16 --spp 1 --point-tris 300";
    size_t i;
    CHECK(tu_run("render landscape --scale 0.05 %s --scene @/recipe.brs --out @/recipe0.png", args) == 0,
          "render landscape failed");
    for (i = 0; i < 2; i++) {
        CHECK(tu_run("render landscape --scale 0.05 %s %s --scene @/recipe.brs --out @/recipe1.png "
                     "--stats @/recipe1.json", args, changes[i]) == 0, "render %s failed", changes[i]);
        CHECK(tu_run("render landscape --scale 0.05 %s %s --scene @/fresh%d.brs --out @/fresh.png", args, changes[i],
                     (int)i) == 0, "render %s into a new file failed", changes[i]);
        EXPECT(tu_json_file_number(tu_scratch("recipe1.json"), "build_seconds") > 0,
               "%s: the scene file of another recipe was reused", changes[i]);
        EXPECT(tu_same_file_bytes(tu_scratch("recipe1.png"), tu_scratch("fresh.png")) &&
                   !tu_same_file_bytes(tu_scratch("recipe1.png"), tu_scratch("recipe0.png")),
               "%s: the image is not that of a fresh scene file", changes[i]);
    }
}

/* ---- the plot writer ---- */

/* The centre of the k-th circle of an SVG; 0 when there is none. */
static int circle(const char *svg, int k, double *cx, double *cy)
{
    const char *p = svg;
    while ((p = strstr(p, "<circle ")) != NULL && k-- > 0) p++;
    return p && sscanf(p, "<circle cx=\"%lf\" cy=\"%lf\"", cx, cy) == 2;
}

static void test_plot_svg(void)
{
    /* Linear axes: x 0..10 and y 0..100 are already whole tick steps, so
    ** the plot area (80..560 by 360..40) maps them exactly; a log2 axis
    ** from 16 to 512 puts 128 at 3/5 of the width. */
    static const double x[] = {0, 5, 10}, y[] = {0, 50, 100}, rx[] = {16, 128, 512};
    static const double ry[] = {1, 10, 100}, bad[] = {0, -1, NAN};
    ex_plot_series series = {"a<b & c", x, y, 3, 0};
    ex_plot plot;
    brt_error err;
    char *svg = NULL;
    double cx, cy;
    int k;
    memset(&plot, 0, sizeof plot);
    plot.title = "t";
    plot.x_label = "x";
    plot.y_label = "y";
    plot.series = &series;
    plot.series_count = 1;
    CHECK(ex_plot_svg(&plot, &svg, &err) == BRT_OK, "%s", err.message);
    for (k = 0; k < 3; k++)
        EXPECT(circle(svg, k, &cx, &cy) && fabs(cx - (80 + 48 * x[k])) < 0.06
               && fabs(cy - (360 - 3.2 * y[k])) < 0.06, "linear point %d at (%g, %g)", k, cx, cy);
    EXPECT(strstr(svg, "a&lt;b &amp; c") && !strstr(svg, "a<b"), "the label is not escaped");
    free(svg);
    series.x = rx;
    series.y = ry;
    plot.x_log_base = 2;
    plot.y_log_base = 10;
    CHECK(ex_plot_svg(&plot, &svg, &err) == BRT_OK, "%s", err.message);
    EXPECT(circle(svg, 1, &cx, &cy) && fabs(cx - (80 + 480 * 0.6)) < 0.06 && fabs(cy - 200) < 0.06,
           "log point at (%g, %g), expected (368, 200)", cx, cy);
    EXPECT(!circle(svg, 3, &cx, &cy), "more circles than points");
    free(svg);
    series.y = bad;
    EXPECT(ex_plot_svg(&plot, &svg, &err) == BRT_EARG && !svg,
           "no positive y on a log axis: not refused");
}

/* The k-th bar of an SVG bar chart; 0 when there is none. */
static int bar(const char *svg, int k, double *x, double *y, double *w, double *h)
{
    const char *p = svg;
    while ((p = strstr(p, "<rect class=\"bar\"")) != NULL && k-- > 0) p++;
    return p && sscanf(p, "<rect class=\"bar\" x=\"%lf\" y=\"%lf\" width=\"%lf\" height=\"%lf\"", x, y, w,
                       h) == 4;
}

static void test_bar_svg(void)
{
    /* Two groups of two bars, values 0..100 on whole tick steps: each group
    ** gets 240 units of the 480-wide area, its bars 0.7 of that (84 each),
    ** from 36 units in; y maps 0..100 to 360..40 exactly.  Bars come out
    ** bar by bar (one colour each), group by group within.  The NaN is
    ** skipped. */
    static const double values[] = {40, 100, 25, NAN}, all_nan[] = {NAN, NAN, NAN, NAN};
    static const double expect_x[] = {116, 356, 200}, expect_v[] = {40, 25, 100};
    static const char *const groups[] = {"g0", "g1"}, *const bars[] = {"a", "b"};
    static const char *const notes[] = {NULL, "5 % & <", "", "n"};
    ex_bar_chart chart;
    brt_error err;
    char *svg = NULL;
    double x, y, w, h;
    int k;
    memset(&chart, 0, sizeof chart);
    chart.title = "t";
    chart.groups = groups;
    chart.group_count = 2;
    chart.bar_labels = bars;
    chart.bar_count = 2;
    chart.values = values;
    chart.notes = notes;
    CHECK(ex_bar_svg(&chart, &svg, &err) == BRT_OK, "%s", err.message);
    for (k = 0; k < 3; k++)
        EXPECT(bar(svg, k, &x, &y, &w, &h) && fabs(x - expect_x[k]) < 0.06 && fabs(w - 84) < 0.06 &&
               fabs(y - (360 - 3.2 * expect_v[k])) < 0.06 && fabs(h - 3.2 * expect_v[k]) < 0.06,
               "bar %d at x %g y %g, %g x %g", k, x, y, w, h);
    EXPECT(!bar(svg, 3, &x, &y, &w, &h), "the NaN got a bar");
    EXPECT(strstr(svg, ">5 % &amp; &lt;</text>") && !strstr(svg, ">n</text>"),
           "the note of a drawn bar is missing or not escaped, or a skipped bar's is drawn");
    free(svg);
    chart.values = all_nan;
    EXPECT(ex_bar_svg(&chart, &svg, &err) == BRT_EARG && !svg, "no finite value: not refused");
}

/* One row of fig4.csv. */
typedef struct fig4_row {
    char scene[32], scheduler[32], proxies[32];
    double bytes, loads, occlusion_rays, occluded, stopped, share, shadow_bytes, proxy_bytes;
} fig4_row;

/* `figures --only 4` on a tiny scene: fig4.csv holds, per scene and
** scheduler, an outer run (no ray stopped by inner proxies) and an outer +
** inner one; the two trace the same shadow rays with the same occluded
** count (inner proxies never change a result), stop at most the occluded
** ones, and the share column is stopped / occluded.  No other figure is
** made.  (Whether inner proxies read fewer bytes is a measurement, not a
** promise: a different load order can cost bytes.) */
static void test_figure4(void)
{
    static const char *const scenes[] = {"landscape", "island"}, *const schedulers[] = {"paper", "batchrt"};
    static const char header[] = "scene,scheduler,proxies,disk_bytes_read,batch_loads,occlusion_rays,"
                                 "occlusion_hits,occlusion_inner_stopped,stopped_share,occlusion_disk_bytes_read,"
                                 "proxy_bytes\n";
    fig4_row rows[8];
    char *csv, *line, *svg;
    int n = 0, k;
    CHECK(tu_run("figures --only 4 --out @/fig --scale 0.05 --point-tris 400 --width 16 --height 10 --spp 1 "
                 "--rays-in-flight 256") == 0, "figures --only 4 failed");
    csv = (char *)tu_slurp(tu_scratch("fig/fig4.csv"), NULL);
    CHECK(csv && strncmp(csv, header, strlen(header)) == 0, "fig4.csv missing or its header wrong");
    for (line = strchr(csv, '\n'); line && line[1] && n < 8; line = strchr(line + 1, '\n')) {
        fig4_row *r = &rows[n++];
        CHECK(sscanf(line + 1, "%31[^,],%31[^,],%31[^,],%lf,%lf,%lf,%lf,%lf,%lf,%lf,%lf", r->scene,
                     r->scheduler, r->proxies, &r->bytes, &r->loads, &r->occlusion_rays, &r->occluded, &r->stopped,
                     &r->share, &r->shadow_bytes, &r->proxy_bytes) == 11, "fig4.csv row %d unreadable", n);
    }
    EXPECT(n == 8 && (!line || !line[1]), "fig4.csv: %d rows, expected 8", n);
    for (k = 0; k + 1 < n; k += 2) {
        const fig4_row *o = &rows[k], *i = &rows[k + 1];
        EXPECT(strcmp(o->scene, scenes[k / 4]) == 0 && strcmp(i->scene, o->scene) == 0 &&
               strcmp(o->scheduler, schedulers[k / 2 % 2]) == 0 && strcmp(i->scheduler, o->scheduler) == 0 &&
               strcmp(o->proxies, "outer") == 0 && strcmp(i->proxies, "outer+inner") == 0,
               "fig4.csv rows %d-%d: %s %s %s / %s %s %s", k, k + 1, o->scene, o->scheduler, o->proxies,
               i->scene, i->scheduler, i->proxies);
        EXPECT(o->stopped == 0 && o->share == 0 && o->occlusion_rays > 0 && i->occlusion_rays == o->occlusion_rays &&
               i->occluded == o->occluded && i->stopped <= i->occluded && o->bytes > 0 && i->bytes > 0 &&
               o->shadow_bytes <= o->bytes && i->shadow_bytes <= i->bytes &&
               o->proxy_bytes == i->proxy_bytes &&
               fabs(i->share - (i->occluded > 0 ? i->stopped / i->occluded : 0)) < 6e-5,
               "%s %s: shadow rays %g/%g, occluded %g/%g, stopped %g/%g, share %g", o->scene, o->scheduler,
               o->occlusion_rays, i->occlusion_rays, o->occluded, i->occluded, o->stopped, i->stopped, i->share);
    }
    svg = (char *)tu_slurp(tu_scratch("fig/fig4.svg"), NULL);
    EXPECT(svg && strstr(svg, "<rect class=\"bar\"") && strstr(svg, "Fig. 4"), "fig4.svg missing or has no bars");
    EXPECT(!tu_file_exists(tu_scratch("fig/fig1.csv")) && !tu_file_exists(tu_scratch("fig/fig3.csv")),
           "--only 4 made other figures");
    free(csv);
    free(svg);
}

/* ---- exact means: scenes whose expected image mean is known ---- */
/*
** The renderer estimates the sky's and the sun's light reflected by grey
** Lambert surfaces (albedo 0.8) over at most MAX_DEPTH - 1 = 7 bounces.
** Two scenes have that sum in closed form, computed here from the sky's
** and the sun's definitions (render.c: sky_radiance's gradient, the sun's
** colour 1, 0.92, 0.78) and geometry alone:
**   - a plane under the sky and a sun: every camera ray hits the plane and
**     every bounce escapes, so the mean is 0.8 times the cosine-weighted
**     sky plus the sun: with mu = cos(angle from the normal) distributed
**     2 mu, E[sqrt(mu)] = 4/5, so the sky gives (1/5) horizon + (4/5)
**     zenith; a disc of radius r at cos(n, s) above the horizon gives
**     L (n.s) sin^2 r (the cosine over the cap, over pi);
**   - an open sphere: the inside of a unit sphere without the cap of
**     half-angle alpha about +y, seen from its centre.  From any point of
**     a sphere's inside a cosine-weighted ray lands uniformly on the
**     sphere's area (the form factor between two of its elements is
**     dA / 4 pi R^2), so each bounce escapes with f = (1 - cos alpha) / 2
**     through a uniform point of the cap, and from the second hit on the
**     hit is uniform over the rest: mean = 0.8 f S1 + S sum over k = 2..7
**     of 0.8^k (1 - f)^(k-1) f, with S1 the sky through the cap from the
**     bottom point (the camera looks down a 1-degree cone: its rays land
**     within a degree of it) and S from a uniform point, integrated here.
**     Two thirds of that light comes after the third hit, where Russian
**     roulette acts, so a roulette that does not reweight its survivors
**     shows at once.
** Each run's mean is checked within 4 standard errors computed from its
** own samples (render's mean_luminance_se): the random numbers are a
** fixed hash, so a given build passes or fails the same way every run.
*/
static const double sky_horizon = (0.45 + 0.50 + 0.58) / 3, sky_zenith = (0.12 + 0.22 + 0.50) / 3;
static const double sun_colour = (1.0 + 0.92 + 0.78) / 3;

/* The luminance of the sky above the horizon along a direction whose y
** component is up (render.c's gradient, independently written). */
static double sky_up(double up)
{
    const double a = sqrt(up);
    return (1 - a) * sky_horizon + a * sky_zenith;
}

/* Runs render with args and checks its mean against expect. */
static void expect_mean(const char *args, double expect)
{
    double mean, se;
    if (tu_run("render %s --stats @/exact.json --out @/exact.png", args) != 0) {
        test_fail_at(__FILE__, __LINE__, "render %s failed: %s", args, tu_last_stderr());
        return;
    }
    mean = tu_json_file_number(tu_scratch("exact.json"), "mean_luminance");
    se = tu_json_file_number(tu_scratch("exact.json"), "mean_luminance_se");
    EXPECT(se > 0 && fabs(mean - expect) <= 4 * se,
           "render %s: mean %.6f, exact %.6f: %.1f standard errors (se %.6f)", args, mean, expect,
           fabs(mean - expect) / se, se);
}

static void test_exact_plane(void)
{
    static const char *const obj = "v -1000 0 -1000\nv 1000 0 -1000\nv 1000 0 1000\nv -1000 0 1000\n"
                                   "f 1 2 3\nf 1 3 4\n";
    const double radius = 8 * 3.14159265358979323846 / 180, cos_ns = sqrt(0.5);
    const double sun = 60 * sun_colour * cos_ns * sin(radius) * sin(radius);
    const double sky = sky_horizon / 5 + 4 * sky_zenith / 5;
    char args[512];
    int nee;
    CHECK(tu_spill(tu_scratch("plane.obj"), obj, strlen(obj)), "could not write plane.obj");
    for (nee = 0; nee < 2; nee++) {
        snprintf(args, sizeof args, "@/plane.obj --scene @/plane.brs --camera 0,2,1:0,0,0:30 "
                 "--width 64 --height 64 --spp %d --sun 1,1,0 --sun-radius 8 --sun-radiance 60 %s",
                 nee ? 16 : 64, nee ? "" : "--no-nee");
        expect_mean(args, 0.8 * (sky + sun));
        snprintf(args, sizeof args, "@/plane.obj --scene @/plane.brs --camera 0,2,1:0,0,0:30 "
                 "--width 32 --height 32 --spp 16 --sun-radiance 0 %s", nee ? "" : "--no-nee");
        expect_mean(args, 0.8 * sky);
    }
}

/* The open sphere's mesh: NT rings of 2 degrees, NP segments, the rings
** above alpha = CAP rings left out. */
#define SPHERE_RINGS 90
#define SPHERE_SEGMENTS 180
#define SPHERE_CAP 30           /* 60 degrees */

static int write_open_sphere(const char *path)
{
    const double pi = 3.14159265358979323846;
    FILE *f = fopen(path, "w");
    int i, j;
    if (!f) return 0;
    for (i = SPHERE_CAP; i <= SPHERE_RINGS; i++)
        for (j = 0; j < SPHERE_SEGMENTS; j++) {
            const double th = pi * i / SPHERE_RINGS, ph = 2 * pi * j / SPHERE_SEGMENTS;
            fprintf(f, "v %.9g %.9g %.9g\n", sin(th) * cos(ph), cos(th), sin(th) * sin(ph));
        }
    for (i = 0; i < SPHERE_RINGS - SPHERE_CAP; i++)
        for (j = 0; j < SPHERE_SEGMENTS; j++) {
            const int a = 1 + i * SPHERE_SEGMENTS + j, b = 1 + i * SPHERE_SEGMENTS + (j + 1) % SPHERE_SEGMENTS;
            fprintf(f, "f %d %d %d\nf %d %d %d\n", a, b, b + SPHERE_SEGMENTS, a, b + SPHERE_SEGMENTS,
                    a + SPHERE_SEGMENTS);
        }
    return fclose(f) == 0;
}

/* The sky through the cap (half-angle alpha) seen from the sphere's
** bottom (first) and from a uniform point of the rest (second): the
** means over a uniform point Q of the cap, by the midpoint rule (the
** bottom: the direction to Q at angle th from the top rises at
** cos(th / 2); a point P at angle tp, azimuth 0 by symmetry). */
static void open_sphere_sky(double alpha, double *from_bottom, double *from_rest)
{
    const double pi = 3.14159265358979323846;
    const int np = 240, nq = 160, nf = 120;
    double sum = 0, weight = 0, sum_p = 0, weight_p = 0;
    int i, j, k;
    for (j = 0; j < nq; j++) {
        const double tq = alpha * (j + 0.5) / nq;
        sum += sin(tq) * sky_up(cos(tq / 2));
        weight += sin(tq);
    }
    *from_bottom = sum / weight;
    for (i = 0; i < np; i++) {
        const double tp = alpha + (pi - alpha) * (i + 0.5) / np;
        const double p[3] = {sin(tp), cos(tp), 0};
        sum = weight = 0;
        for (j = 0; j < nq; j++) {
            const double tq = alpha * (j + 0.5) / nq;
            for (k = 0; k < nf; k++) {
                const double fq = pi * (k + 0.5) / nf;   /* symmetric in the azimuth's sign */
                const double d[3] = {sin(tq) * cos(fq) - p[0], cos(tq) - p[1], sin(tq) * sin(fq)};
                sum += sin(tq) * sky_up(d[1] / sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]));
                weight += sin(tq);
            }
        }
        sum_p += sin(tp) * sum / weight;
        weight_p += sin(tp);
    }
    *from_rest = sum_p / weight_p;
}

static void test_exact_open_sphere(void)
{
    const double alpha = 3.14159265358979323846 * SPHERE_CAP / SPHERE_RINGS, f = (1 - cos(alpha)) / 2;
    double s1, s, expect, stay = 1, albedo = 0.8;
    int k, nee;
    CHECK(write_open_sphere(tu_scratch("sphere.obj")), "could not write sphere.obj");
    open_sphere_sky(alpha, &s1, &s);
    expect = 0.8 * f * s1;
    for (k = 2; k <= 7; k++) {
        albedo *= 0.8;
        stay *= 1 - f;
        expect += albedo * stay * f * s;
    }
    for (nee = 0; nee < 2; nee++)
        expect_mean(nee ? "@/sphere.obj --scene @/sphere.brs --camera 0,0,0:0,-1,0:1 --width 16 "
                          "--height 16 --spp 512 --sun-radiance 0"
                        : "@/sphere.obj --scene @/sphere.brs --camera 0,0,0:0,-1,0:1 --width 16 "
                          "--height 16 --spp 512 --sun-radiance 0 --no-nee",
                    expect);
}

/* render's default point size follows trace's rule (README, "The
** default point size"): never below 100000 triangles, so on the crown at
** scale 0.3 (about 30 000 triangles) the default makes the scene file
** --point-tris 100000 makes, not the one of 10000.  Above the floor:
** tests/test_point_size.c. */
static void test_default_point_size(void)
{
    const char *args = "crown --scale 0.3 --width 4 --height 4 --spp 1 --proxy-res 8";
    double points, hundred_k, ten_k;
    CHECK(tu_run("render %s --scene @/dp.brs --out @/dp.png --stats @/dp.json", args) == 0, "render: %s",
          tu_last_stderr());
    CHECK(tu_run("render %s --point-tris 100000 --scene @/dp1.brs --out @/dp.png --stats @/dp1.json", args) == 0 &&
          tu_run("render %s --point-tris 10000 --scene @/dp2.brs --out @/dp.png --stats @/dp2.json", args) == 0,
          "render: %s", tu_last_stderr());
    points = tu_json_file_number(tu_scratch("dp.json"), "batching_points");
    hundred_k = tu_json_file_number(tu_scratch("dp1.json"), "batching_points");
    ten_k = tu_json_file_number(tu_scratch("dp2.json"), "batching_points");
    CHECK(ten_k > hundred_k, "the scene is too small to tell the sizes apart (%g and %g points)", ten_k, hundred_k);
    EXPECT(points == hundred_k, "default: %g batching points, --point-tris 100000: %g", points, hundred_k);
}

/* One make bench-island at a small scale (keep: SCALE_KEEP=1); its
** standard output (malloc'd), and its Fig. 3 point in *shown, checked
** against the two runs' statistics. */
static char *bench_island_small(int keep, double *shown)
{
    char args[PATH_MAX + 256], path[PATH_MAX], *out;
    const char *fig3;
    double with, without;
    *shown = -1.0;
    snprintf(args, sizeof args, "make -s bench-island BUILD='%s' ISLAND_SCALE=1 ISLAND_TRIS=20000 "
             "ISLAND_INSTANCED=500000 ISLAND_MEMORY=16M ISLAND_DIR='@/island' SCALE_KEEP=%d",
             getenv("BRT_BUILD") ? getenv("BRT_BUILD") : "build", keep);
    if (tu_shell("", args, "") != 0) return NULL;
    out = tu_last_stdout();
    fig3 = out ? strstr(out, "Fig. 3 at 60 %, the paper's scheduler: ") : NULL;
    if (fig3) fig3 = strstr(fig3, "with: ");
    EXPECT(fig3 && sscanf(fig3, "with: %lf", shown) == 1, "no Fig. 3 point in: %s", out ? out : "");
    tu_expand_scratch("@/island/fig3.json", path, sizeof path);
    with = tu_json_file_number(path, "disk_bytes_read");
    tu_expand_scratch("@/island/fig3--no-proxy.json", path, sizeof path);
    without = tu_json_file_number(path, "disk_bytes_read");
    EXPECT(without > 0 && fabs(*shown - with / without) <= 0.005, "Fig. 3 point %.2f, the runs read %.0f and %.0f "
           "bytes (%.4f)", *shown, with, without, with / without);
    EXPECT(out && strstr(out, "render: peak RSS") && !strstr(out, "VIOLATED"), "the memory statements: %s",
           out ? out : "");
    return out;
}

/* The render bound bench-island printed (out) is the README's statement,
** recomputed from its statistics and its scene file: the limit, 280 B per
** path, 512 B per point, 40 B per pixel, 16 MiB, and with threads the
** largest point's blob read ahead and 1 MiB per thread. */
static void island_render_bound(const char *out, const char *scene_path)
{
    char json[PATH_MAX];
    const double mib = 1048576.0, cores = (double)brt_threads_resolve(0);
    double largest = 0, want, got = -1;
    brt_scene *scene = NULL;
    brt_error err;
    const char *at = strstr(out, "render: peak RSS");
    uint32_t id;
    CHECK(brt_scene_open(scene_path, &scene, &err) == BRT_OK, "%s", err.message);
    for (id = 0; id < scene->header.point_count; id++)
        if ((double)scene->blobs[id].size > largest) largest = (double)scene->blobs[id].size;
    brt_scene_close(scene);
    tu_expand_scratch("@/island/render.json", json, sizeof json);
    want = (tu_json_file_number(json, "memory_limit") + 280 * tu_json_file_number(json, "paths_in_flight") +
            512 * tu_json_file_number(json, "batching_points") + 40.0 * 320 * 180 + 16 * mib +
            (cores > 1 ? largest + cores * mib : 0)) / mib;
    if (at) at = strstr(at, "<= bound ");
    EXPECT(at && sscanf(at, "<= bound %lf", &got) == 1 && fabs(got - want) <= 0.06,
           "render: bound %.2f MiB, the README's %.2f", got, want);
}

/* make bench-island at a small scale (README, "Memory", "Benchmarks"): it
** exits 0, the memory statements print "holds", and its Fig. 3 point is
** the two runs' disk bytes, with proxies over without, as their statistics
** say; the scene file is removed, or with SCALE_KEEP=1 kept and reused
** (no build the second time) for the same point. */
static void test_bench_island_small(void)
{
    char path[PATH_MAX], *out;
    double first, kept, reused;
    if (!tu_rss_is_meaningful()) return;   /* its memory checks: not under a sanitizer or valgrind */
    CHECK((out = bench_island_small(0, &first)) != NULL, "make bench-island failed");
    EXPECT(strstr(out, "build from the generator: peak RSS") != NULL, "no build check: %s", out);
    free(out);
    tu_expand_scratch("@/island/island.brs", path, sizeof path);
    EXPECT(!tu_file_exists(path), "the scene file was kept without SCALE_KEEP=1");
    CHECK((out = bench_island_small(1, &kept)) != NULL, "make bench-island SCALE_KEEP=1 failed");
    EXPECT(tu_file_exists(path), "SCALE_KEEP=1 did not keep the scene file");
    island_render_bound(out, path);
    free(out);
    CHECK((out = bench_island_small(1, &reused)) != NULL, "make bench-island on a kept scene file failed");
    EXPECT(strstr(out, "kept by SCALE_KEEP=1: no build") && !strstr(out, "build from the generator"),
           "the kept scene file was not reused: %s", out);
    EXPECT(first == kept && kept == reused, "Fig. 3 points %.2f, %.2f (kept), %.2f (reused)", first, kept, reused);
    free(out);
}

/* The voxelization a scene file's proxies were built with, from its
** header (offset 200 of an instanced file); 0 when unreadable. */
static uint32_t scene_voxelization(const char *path)
{
    size_t size = 0;
    unsigned char *bytes = tu_slurp(path, &size);
    uint32_t mode = bytes && size >= 256 ? brt_get_le32(bytes + 200) : 0;
    free(bytes);
    return mode;
}

/* render --exact-voxels (analysis): its proxies are the every-triangle
** ones, so the image is the same bytes; the file --scene names is the one
** built, and rebuilt whenever the voxelization asked for is not the
** file's; without --scene the file has a name of its own. */
static void test_exact_voxels_scene_files(void)
{
    static const char *const runs[3] = {"", " --exact-voxels", ""};
    static const uint32_t want[3] = {INSTANCE_VOXELS_PRUNED, INSTANCE_VOXELS_EVERY_TRIANGLE, INSTANCE_VOXELS_PRUNED};
    const char *scene = tu_scratch("v.brs");
    char own[PATH_MAX];
    DIR *dir;
    struct dirent *e;
    int i, found = 0;
    for (i = 0; i < 3; i++) {
        CHECK(tu_run("render landscape --scale 0.02 --spp 1 --width 16 --height 8 --scene @/v.brs --out @/v%d.png%s",
                     i, runs[i]) == 0, "render%s failed", runs[i]);
        EXPECT(scene_voxelization(scene) == want[i], "run %d%s: the scene file's voxelization is %u, want %u", i,
               runs[i], (unsigned)scene_voxelization(scene), (unsigned)want[i]);
    }
    EXPECT(!tu_file_exists(tu_scratch("v-exact-voxels.brs")), "--exact-voxels renamed the file --scene names");
    EXPECT(tu_same_file_bytes(tu_scratch("v0.png"), tu_scratch("v1.png")), "--exact-voxels changed the image");
    setenv("BRT_SCENE_DIR", tu_scratch("own"), 1);
    EXPECT(tu_run("render landscape --scale 0.02 --spp 1 --width 16 --height 8 --exact-voxels --out @/v3.png") == 0,
           "render --exact-voxels without --scene failed");
    unsetenv("BRT_SCENE_DIR");
    snprintf(own, sizeof own, "%s", tu_scratch("own"));
    for (dir = opendir(own); dir && (e = readdir(dir)) != NULL;) {
        const size_t n = strlen(e->d_name);
        found += n > 17 && strcmp(e->d_name + n - 17, "-exact-voxels.brs") == 0;
    }
    if (dir) closedir(dir);
    EXPECT(found == 1, "%d scene files named *-exact-voxels.brs in $BRT_SCENE_DIR", found);
}

/* The bound make bench-scale prints after "WHAT: peak RSS X MiB <= bound",
** in MiB, or -1. */
static double printed_bound(const char *out, const char *what)
{
    const char *p = strstr(out, what);
    double bound = -1.0;
    if (p) p = strstr(p, "<= bound ");
    if (p && sscanf(p, "<= bound %lf", &bound) != 1) bound = -1.0;
    return bound;
}

/* make bench-scale at a small scale: its two build bounds are the README's
** statement (256 MiB, 12 B per vertex of the OBJ, the DAG, 64 B per
** prototype triangle, 256 B per triangle of a point per core, and what
** the one-pixel render read), computed here from its statistics files. */
static void test_bench_scale_small(void)
{
    char args[PATH_MAX + 256], path[PATH_MAX], *out, *mk;
    const double mib = 1048576.0, cores = (double)brt_threads_resolve(0);   /* getconf _NPROCESSORS_ONLN */
    unsigned long tris = 0, verts = 0, proto = 0;
    double want, got;
    if (!tu_rss_is_meaningful()) return;   /* its memory checks: not under a sanitizer or valgrind */
    snprintf(args, sizeof args, "make -s bench-scale BUILD='%s' SCALE_OBJ=0.2 SCALE_LAND=0.05 SCALE_BATCH=7000 "
             "SCALE_INSTANCED=300000 SCALE_MEMORY=8M SCALE_DIR='@/scale'",
             getenv("BRT_BUILD") ? getenv("BRT_BUILD") : "build");
    CHECK(tu_shell("", args, "") == 0, "make bench-scale failed");
    out = tu_last_stdout();
    CHECK(out != NULL, "no output");
    tu_expand_scratch("@/scale/mkscene.txt", path, sizeof path);
    mk = (char *)tu_slurp(path, NULL);
    CHECK(mk && sscanf(mk, "crown: %lu triangles, %lu vertices", &tris, &verts) == 2, "mkscene's line: %s",
          mk ? mk : "(none)");
    tu_expand_scratch("@/scale/obj.json", path, sizeof path);
    want = (256 * mib + 12.0 * verts + tu_json_file_number(path, "proxy_bytes") + cores * 256 * 7000 +
            tu_json_file_number(path, "disk_bytes_read")) / mib;
    got = printed_bound(out, "build from the OBJ");
    EXPECT(fabs(got - want) <= 0.06, "build from the OBJ: bound %.2f MiB, the README's %.2f", got, want);
    tu_expand_scratch("@/scale/land.txt", path, sizeof path);
    free(mk);
    mk = (char *)tu_slurp(path, NULL);
    CHECK(mk && strstr(mk, " in prototypes)") && sscanf(strchr(mk, '(') + 1, "%lu", &proto) == 1, "render's line");
    tu_expand_scratch("@/scale/land-build.json", path, sizeof path);
    want = (256 * mib + tu_json_file_number(path, "proxy_bytes") + 64.0 * proto + cores * 256 * 7000 +
            tu_json_file_number(path, "disk_bytes_read")) / mib;
    got = printed_bound(out, "build from the generator");
    EXPECT(fabs(got - want) <= 0.06, "build from the generator: bound %.2f MiB, the README's %.2f", got, want);
    EXPECT(!strstr(out, "VIOLATED"), "a memory statement failed: %s", out);
    free(mk);
    free(out);
}

void suite_render(void)
{
    test_run("render: default point size, the rule's floor of 100000 on a small scene", test_default_point_size);
    test_run("render: help", test_help);
    test_run("render: --exact-voxels, the same image; its scene file rebuilt, or one of its own",
             test_exact_voxels_scene_files);
    test_run("render: make bench-island at a small scale, its Fig. 3 point and memory checks, kept and reused",
             test_bench_island_small);
    test_run("render: make bench-scale at a small scale: its build bounds are the README's", test_bench_scale_small);
    test_run("render: same image in every mode", test_same_image_every_mode);
    test_run("render: same image from a mesh file", test_same_image_mesh_file);
    test_run("render: shadow rays, same image in every mode, with and without",
             test_nee_same_image_every_mode);
    test_run("render: next-event estimation and --no-nee converge to the same mean",
             test_nee_converges_to_no_nee);
    test_run("render: exact mean, a plane under the sky and a sun", test_exact_plane);
    test_run("render: exact mean, an open sphere over every depth", test_exact_open_sphere);
    test_run("render: --pfm and --reference (RMSE)", test_pfm_reference);
    test_run("render: heatmap counts every queued visit", test_heatmap);
    test_run("render: compare table", test_compare);
    test_run("render: --disk-speed makes loads last bytes / speed", test_disk_speed);
    test_run("render: bad options exit 1 and write nothing", test_bad_options);
    test_run("render: every built-in scene, streamed build == --direct", test_builtin_scenes_streamed);
    test_run("render: a reused built-in scene file holds no mesh", test_reused_builtin_holds_no_mesh);
    test_run("render: a built-in scene's file is rebuilt for another scale or seed", test_builtin_scene_rebuilt_for_its_recipe);
    test_run("render: plot svg", test_plot_svg);
    test_run("render: bar chart svg", test_bar_svg);
    test_run("render: figures --only 4 (inner proxies' table)", test_figure4);
}
