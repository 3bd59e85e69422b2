/*
** examples/tools/figures.c -- the figures of Molenaar and Eisemann (2020),
** "Conservative Ray Batching using Geometry Proxies", on the built-in
** scenes (`make figures`):
**
**   Fig. 1  batching points visited per sample, without and with proxies:
**           heatmaps (PNG) and their means (fig1.csv);
**   Fig. 2  proxy memory and effectiveness (share of top-level visits
**           culled) against proxy resolution 16..512 (fig2.csv, SVG);
**   Fig. 3  total disk bytes read against the memory limit, 10 %..100 % of
**           the geometry bytes, without and with proxies, with exactly
**           voxelized proxies (render --exact-voxels) and with exact
**           proxies (render --exact-proxy: the bound on what any
**           conservative proxy can save) (fig3.csv, SVG);
**   Fig. 4  (not in the paper: its section 4.3's future work, README "Inner
**           proxies") disk bytes read at 25 % of the geometry bytes on the
**           landscape and the island with next-event estimation, outer
**           proxies alone (render --no-inner) against outer + inner, and the
**           share of occluded shadow rays that inner proxies stopped before
**           any queue (fig4.csv, a bar chart).
**
**   build/figures [--out DIR] [--only N] [--scale S] [--point-tris N]
**                 [--spp N] [--width W] [--height H] [--rays-in-flight N]
**                 [--threads N]
**
** Every number comes from build/render (the program next to this one) and
** its statistics JSON, so the figures measure exactly what a user runs.
** Each figure's table is printed on stdout as Markdown, the paper's values
** beside it (the README's tables are this output); progress goes to
** stderr.
** Its output goes to DIR/render.log.  As in the paper, with proxies
** on the memory limit also pays for the proxies, and every ray is queued
** (render --paper-scheduler: the paper's scheduler; by default render
** intersects rays at once at batching points in memory, which skips their
** proxies, so the figures would no longer measure what the proxies cull).
** Fig. 3 is drawn for batchrt's own scheduler as well (four more lines), so
** the two can be compared.  Scene files are
** built once per resolution in the default scene folder and reused.
** Fig. 1 is a picture, rendered with the sun's shadow rays (next-event
** estimation, render's default, whose rays count among the visits);
** Figs. 2 and 3 trace the paths alone (render --no-nee), the workload
** their README tables were measured on; Fig. 4 needs the shadow rays.
** Figs. 3 and 4 are drawn for both schedulers.
*/
#include "plot.h"
#include "scenes.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <errno.h>

static const char *const prog = "figures";

#define RES_COUNT 6
#define LIMIT_COUNT 10
#define SCENE_COUNT 3
#define FIGURE_COUNT 4

static const char *const scene_names[SCENE_COUNT] = {"crown", "landscape", "island"};
static const double resolutions[RES_COUNT] = {16, 32, 64, 128, 256, 512};

typedef struct settings {
    const char *out;
    int only;                 /* 1..FIGURE_COUNT: that figure alone; 0: all */
    int paper;                /* --paper: Fig. 3 alone, in the paper's regime */
    double scale;
    uint64_t point_tris, spp, width, height, rays_in_flight, threads;
    uint64_t point_instanced; /* render --point-instanced; 0: not given */
    char render[4096];        /* path of build/render */
} settings;

static void usage(void)
{
    printf("usage: build/figures [options]\n"
           "The paper's Figs. 1-3 on the built-in scenes (crown, landscape, island),\n"
           "and Fig. 4, inner proxies (landscape, island: disk bytes at 25 %% memory with\n"
           "and without them, shadow rays they stop), measured with build/render:\n"
           "PNG heatmaps, CSV tables and SVG plots.\n"
           "\n"
           "  --out DIR            output folder (default figures)\n"
           "  --only N             figure N (1-4) alone (default: all four)\n"
           "  --scale S            scene size, about 100000*S triangles (default 4)\n"
           "  --point-tris N       triangles per batching point (default 30000)\n"
           "  --spp N              samples per pixel (default 4)\n"
           "  --width W            image width (default 160)\n"
           "  --height H           image height (default 90)\n"
           "  --rays-in-flight N   paths traced at once (default 16384)\n"
           "  --threads N          threads of each render (default 0: all cores)\n"
           "  --point-instanced N  instanced triangles per batching point (render's option;\n"
           "                       default 2000000)\n"
           "  --paper              Fig. 3 alone in the paper's regime: the instanced landscape\n"
           "                       and island, limits 60-90 %% (make bench-paper)\n"
           "  --help               this text\n");
}

/* build/render sits next to this program. */
static void find_render(const char *argv0, settings *s)
{
    const char *slash = strrchr(argv0, '/');
    int dir = slash ? (int)(slash - argv0) : 1;
    snprintf(s->render, sizeof s->render, "%.*s/render", dir, slash ? argv0 : ".");
}

static void parse_options(int argc, char **argv, settings *s)
{
    int i;
    memset(s, 0, sizeof *s);
    s->out = "figures";
    s->scale = 4;
    s->point_tris = 30000;
    s->point_instanced = 2000000;   /* the instanced scenes' points: see the README */
    s->spp = 4;
    s->width = 160;
    s->height = 90;
    s->rays_in_flight = 16384;
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
#define VALUE ex_option_value(prog, argc, argv, &i)
        if (strcmp(a, "--out") == 0) s->out = VALUE;
        else if (strcmp(a, "--only") == 0) s->only = (int)ex_parse_u64(prog, a, VALUE, 1, FIGURE_COUNT);
        else if (strcmp(a, "--scale") == 0) s->scale = ex_parse_double(prog, a, VALUE, 0.001, EX_SCENE_MAX_SCALE);
        else if (strcmp(a, "--point-tris") == 0) s->point_tris = ex_parse_u64(prog, a, VALUE, 1, UINT32_MAX);
        else if (strcmp(a, "--spp") == 0) s->spp = ex_parse_u64(prog, a, VALUE, 1, 65536);
        else if (strcmp(a, "--width") == 0) s->width = ex_parse_u64(prog, a, VALUE, 1, 16384);
        else if (strcmp(a, "--height") == 0) s->height = ex_parse_u64(prog, a, VALUE, 1, 16384);
        else if (strcmp(a, "--rays-in-flight") == 0)
            s->rays_in_flight = ex_parse_u64(prog, a, VALUE, 1, 1u << 26);
        else if (strcmp(a, "--threads") == 0) s->threads = ex_parse_u64(prog, a, VALUE, 0, BRT_MAX_THREADS);
        else if (strcmp(a, "--point-instanced") == 0)
            s->point_instanced = ex_parse_u64(prog, a, VALUE, 1, UINT64_MAX);
        else if (strcmp(a, "--paper") == 0) s->paper = s->only = 3;
        else if (a[0] == '-') ex_unknown_option(prog, a);
        else ex_die(prog, "unknown argument '%s' (see --help)", a);
#undef VALUE
    }
    /* The folder goes into shell commands inside single quotes. */
    if (strchr(s->out, '\'')) ex_die(prog, "--out: a folder name with a quote is not supported");
    if (mkdir(s->out, 0755) != 0 && errno != EEXIST)
        ex_die(prog, "%s: cannot create: %s", s->out, strerror(errno));
    find_render(argv[0], s);
}

/* DIR/name, in one of a few rotating buffers: copy it to keep it. */
static const char *out_path(const settings *s, const char *name)
{
    static char paths[4][4096];
    static int next;
    char *p = paths[next++ % 4];
    snprintf(p, sizeof paths[0], "%s/%s", s->out, name);
    return p;
}

/* The two schedulers: the paper's, and batchrt's default. */
enum { PAPER_SCHEDULER, BATCHRT_SCHEDULER };

/* Runs build/render on a built-in scene with the common settings, the
** given scheduler and extra arguments, its output appended to
** DIR/render.log. */
static void run_render(const settings *s, const char *scene, int scheduler, const char *extra)
{
    char command[32768], instanced[64] = "";
    if (s->point_instanced)
        snprintf(instanced, sizeof instanced, "--point-instanced %llu",
                 (unsigned long long)s->point_instanced);
    snprintf(command, sizeof command,
             "'%s' %s --grey %s --scale %g --point-tris %llu --spp %llu --width %llu --height %llu "
             "--rays-in-flight %llu --threads %llu %s %s >>'%s' 2>&1",
             s->render, scene, instanced, s->scale, (unsigned long long)s->point_tris,
             (unsigned long long)s->spp, (unsigned long long)s->width,
             (unsigned long long)s->height, (unsigned long long)s->rays_in_flight,
             (unsigned long long)s->threads, scheduler == PAPER_SCHEDULER ? "--paper-scheduler" : "", extra,
             out_path(s, "render.log"));
    if (system(command) != 0)
        ex_die(prog, "build/render failed on %s (see %s)", scene, out_path(s, "render.log"));
}

/* A number field of a statistics JSON file ("name": value). */
static double json_number(const char *path, const char *name)
{
    char line[512], key[128];
    FILE *f = fopen(path, "r");
    double value = 0;
    int found = 0;
    if (!f) ex_die(prog, "%s: %s", path, strerror(errno));
    snprintf(key, sizeof key, "\"%s\":", name);
    while (!found && fgets(line, sizeof line, f)) {
        const char *p = strstr(line, key);
        if (p) found = sscanf(p + strlen(key), "%lf", &value) == 1;
    }
    fclose(f);
    if (!found) ex_die(prog, "%s: no number \"%s\"", path, name);
    return value;
}

static FILE *open_csv(const settings *s, const char *name, const char *header)
{
    FILE *f = fopen(out_path(s, name), "w");
    if (!f) ex_die(prog, "%s: %s", out_path(s, name), strerror(errno));
    fprintf(f, "%s\n", header);
    return f;
}

static void close_csv(const settings *s, FILE *f, const char *name)
{
    if (fclose(f) != 0) ex_die(prog, "%s: write error", out_path(s, name));
}

static void write_plot(const settings *s, const char *name, const ex_plot *plot)
{
    brt_error err;
    ex_check(prog, ex_plot_write_svg(out_path(s, name), plot, &err), &err);
}

/* ---- Fig. 1 ---- */

/* Heatmaps without and with proxies (one colour scale; render --compare). */
static void figure1(const settings *s)
{
    FILE *csv = open_csv(s, "fig1.csv", "scene,visits_per_sample_no_proxy,visits_per_sample_proxy,ratio");
    char extra[16384], name[64];
    double ratios[SCENE_COUNT][2];
    int i;
    for (i = 0; i < SCENE_COUNT; i++) {
        double without, with;
        /* Twice the width and height of the other figures: these are pictures. */
        snprintf(extra, sizeof extra, "--width %llu --height %llu --compare --out '%s/fig1_%s.png' "
                 "--heatmap '%s/fig1_%s_heat.png' --stats '%s/fig1_%s.json'",
                 2 * (unsigned long long)s->width, 2 * (unsigned long long)s->height, s->out,
                 scene_names[i], s->out, scene_names[i], s->out, scene_names[i]);
        fprintf(stderr, "Fig. 1: %s\n", scene_names[i]);
        run_render(s, scene_names[i], PAPER_SCHEDULER, extra);
        snprintf(name, sizeof name, "fig1_%s-noproxy.json", scene_names[i]);
        without = json_number(out_path(s, name), "visits_per_sample");
        snprintf(name, sizeof name, "fig1_%s.json", scene_names[i]);
        with = json_number(out_path(s, name), "visits_per_sample");
        fprintf(csv, "%s,%.4f,%.4f,%.4f\n", scene_names[i], without, with, with / without);
        ratios[i][0] = without;
        ratios[i][1] = with;
    }
    close_csv(s, csv, "fig1.csv");
    printf("\nFig. 1, batching points visited per sample (the paper: roughly halved)\n\n"
           "| scene | without proxies | with proxies | ratio |\n|---|---:|---:|---:|\n");
    for (i = 0; i < SCENE_COUNT; i++)
        printf("| %s | %.2f | %.2f | %.2f |\n", scene_names[i], ratios[i][0], ratios[i][1],
               ratios[i][1] / ratios[i][0]);
}

/* ---- Fig. 2 ---- */

static void figure2(const settings *s)
{
    FILE *csv = open_csv(s, "fig2.csv", "scene,resolution,proxy_bytes,proxy_tests,proxy_culled,"
                                        "culled_share,visits_per_sample");
    static double memory[SCENE_COUNT][RES_COUNT], culled[SCENE_COUNT][RES_COUNT];
    ex_plot_series mem_series[SCENE_COUNT], cull_series[SCENE_COUNT];
    ex_plot plot;
    char extra[12288], stats[4096];
    int i, r;
    snprintf(stats, sizeof stats, "%s", out_path(s, "fig2_run.json"));
    for (i = 0; i < SCENE_COUNT; i++) {
        fprintf(stderr, "Fig. 2: %s, resolution", scene_names[i]);
        for (r = 0; r < RES_COUNT; r++) {
            double bytes, tests, culls;
            fprintf(stderr, " %g", resolutions[r]);
            snprintf(extra, sizeof extra, "--proxy-res %g --no-nee --out '%s/run.png' --stats '%s'", resolutions[r], s->out,
                     stats);
            run_render(s, scene_names[i], PAPER_SCHEDULER, extra);
            bytes = json_number(stats, "proxy_bytes");
            tests = json_number(stats, "proxy_tests");
            culls = json_number(stats, "proxy_culled");
            memory[i][r] = bytes / 1048576.0;
            culled[i][r] = tests > 0 ? 100.0 * culls / tests : 0;
            fprintf(csv, "%s,%g,%.0f,%.0f,%.0f,%.4f,%.4f\n", scene_names[i], resolutions[r], bytes,
                    tests, culls, culled[i][r] / 100.0, json_number(stats, "visits_per_sample"));
        }
        fprintf(stderr, "\n");
        mem_series[i].label = cull_series[i].label = scene_names[i];
        mem_series[i].x = cull_series[i].x = resolutions;
        mem_series[i].y = memory[i];
        cull_series[i].y = culled[i];
        mem_series[i].count = cull_series[i].count = RES_COUNT;
        mem_series[i].dashed = cull_series[i].dashed = 0;
    }
    close_csv(s, csv, "fig2.csv");
    printf("\nFig. 2, proxy memory (the shared DAG, MiB) and share of proxy tests culled, against "
           "resolution\n\n| resolution |");
    for (i = 0; i < SCENE_COUNT; i++) printf(" %s MiB | %s culled |", scene_names[i], scene_names[i]);
    printf("\n|---:|");
    for (i = 0; i < SCENE_COUNT; i++) printf("---:|---:|");
    printf("\n");
    for (r = 0; r < RES_COUNT; r++) {
        printf("| %g |", resolutions[r]);
        for (i = 0; i < SCENE_COUNT; i++) printf(" %.2f | %.0f %% |", memory[i][r], culled[i][r]);
        printf("\n");
    }
    remove(stats);
    remove(out_path(s, "run.png"));
    memset(&plot, 0, sizeof plot);
    plot.title = "Fig. 2a: proxy memory (shared DAG) against resolution";
    plot.x_label = "proxy resolution (voxels per side)";
    plot.y_label = "proxy memory (MiB)";
    plot.x_log_base = 2;
    plot.y_log_base = 10;
    plot.series = mem_series;
    plot.series_count = SCENE_COUNT;
    write_plot(s, "fig2_memory.svg", &plot);
    plot.title = "Fig. 2b: share of top-level visits culled by the proxy";
    plot.y_label = "culled (% of proxy tests)";
    plot.y_log_base = 0;
    plot.y_from_zero = 1;
    plot.series = cull_series;
    write_plot(s, "fig2_culled.svg", &plot);
}

/* ---- Fig. 3 ---- */

/* The eight runs at each limit: series 4 * scheduler + proxy kind.  The
** exactly voxelized proxies (render --exact-voxels: every instanced
** triangle tested, none pruned) against the proxies show what the
** voxelization loses, the exact proxies against them what the resolution
** does. */
#define PROXY_KINDS 4
#define FIG3_SERIES (2 * PROXY_KINDS)
static const char *const proxy_kinds[PROXY_KINDS] = {"none", "voxels", "exact-voxels", "exact"};
static const char *const proxy_options[PROXY_KINDS] = {"--no-proxy", "", "--exact-voxels",
                                                       "--exact-proxy"};

/* Disk MiB and the share of proxy tests culled at limit[l] %, per
** scheduler and proxy kind. */
typedef struct fig3_runs {
    double disk[FIG3_SERIES][LIMIT_COUNT], culled[FIG3_SERIES][LIMIT_COUNT];
} fig3_runs;

static void figure3_scene(const settings *s, FILE *csv, int i, double limits[LIMIT_COUNT],
                          fig3_runs *runs)
{
    static const char *const scheduler_names[2] = {"paper", "batchrt"};
    char extra[12288], stats[4096];
    int l, run, scheduler;
    snprintf(stats, sizeof stats, "%s", out_path(s, "fig3_run.json"));
    fprintf(stderr, "Fig. 3: %s, limit %%", scene_names[i]);
    for (l = 0; l < LIMIT_COUNT; l++) {
        limits[l] = 10.0 * (l + 1);
        for (run = 0; run < FIG3_SERIES; run++) runs->disk[run][l] = runs->culled[run][l] = NAN;
        if (s->paper && (l < 5 || l > 8)) continue;   /* the paper's 60..90 % */
        fprintf(stderr, " %g", limits[l]);
        for (run = 0; run < FIG3_SERIES; run++) {
            int kind = run % PROXY_KINDS;
            double tests;
            scheduler = run / PROXY_KINDS;
            snprintf(extra, sizeof extra, "--memory %g%% %s --no-nee --out '%s/run.png' --stats '%s'",
                     limits[l], proxy_options[kind], s->out, stats);
            run_render(s, scene_names[i], scheduler, extra);
            runs->disk[run][l] = json_number(stats, "disk_bytes_read") / 1048576.0;
            tests = json_number(stats, "proxy_tests");
            runs->culled[run][l] = tests > 0 ? 100.0 * json_number(stats, "proxy_culled") / tests : 0;
            fprintf(csv, "%s,%s,%g,%s,%.0f,%.0f,%.0f,%.0f,%.0f,%.0f,%.4f\n", scene_names[i],
                    scheduler_names[scheduler], limits[l], proxy_kinds[kind],
                    json_number(stats, "disk_bytes_read"), json_number(stats, "batch_loads"),
                    json_number(stats, "geometry_bytes"), json_number(stats, "proxy_bytes"),
                    tests, json_number(stats, "proxy_culled"), json_number(stats, "seconds"));
        }
    }
    fprintf(stderr, "\n");
    remove(stats);
    remove(out_path(s, "run.png"));
}

/* The paper's range, 60..90 %: for each scheduler, the disk bytes of the
** proxies, the exactly voxelized ones and the exact ones over none's, each
** with the share of proxy tests it culled; the paper's ratios (its Fig. 3)
** below. */
static void figure3_table(const settings *s, const double limits[LIMIT_COUNT],
                          double ratio[SCENE_COUNT][FIG3_SERIES][LIMIT_COUNT],
                          double culled[SCENE_COUNT][FIG3_SERIES][LIMIT_COUNT])
{
    const int first = s->paper ? 1 : 0;   /* --paper: the instanced scenes alone */
    static const char *const paper[SCENE_COUNT] = {"0.73-0.81", "0.60-0.77", "0.46-0.52"};
    int scheduler, i, l, kind;
    printf("\nFig. 3, disk bytes with proxies / without, proxies paid out of the limit, and the "
           "share of proxy tests culled: the proxies, the exactly voxelized, the exact (the bound)"
           "\n\n| scheduler | limit |");
    for (i = first; i < SCENE_COUNT; i++)
        printf(" %s | exactly voxelized | exact |", scene_names[i]);
    printf("\n|---|---:|");
    for (i = first; i < SCENE_COUNT; i++) printf("---:|---:|---:|");
    printf("\n");
    for (scheduler = 0; scheduler < 2; scheduler++)
        for (l = 5; l < 9; l++) {
            printf("| %s | %g %% |", scheduler ? "batchrt's" : "paper's", limits[l]);
            for (i = first; i < SCENE_COUNT; i++)
                for (kind = 1; kind < PROXY_KINDS; kind++)
                    printf(" %.2f, %.0f %% |", ratio[i][PROXY_KINDS * scheduler + kind][l],
                           culled[i][PROXY_KINDS * scheduler + kind][l]);
            printf("\n");
        }
    printf("| the paper | 60-90 %% |");
    for (i = first; i < SCENE_COUNT; i++) printf(" %s | | |", paper[i]);
    printf("\n");
}

static void figure3(const settings *s)
{
    static const char *const labels[FIG3_SERIES] = {   /* scheduler: proxies */
        "paper: no proxies", "paper: proxies", "paper: exactly voxelized", "paper: exact",
        "batchrt: no proxies", "batchrt: proxies", "batchrt: exactly voxelized", "batchrt: exact"};
    FILE *csv = open_csv(s, "fig3.csv", "scene,scheduler,limit_percent,proxies,disk_bytes_read,"
                                        "batch_loads,geometry_bytes,proxy_bytes,proxy_tests,"
                                        "proxy_culled,seconds");
    double limits[LIMIT_COUNT];
    static fig3_runs runs;
    static double ratio[SCENE_COUNT][FIG3_SERIES][LIMIT_COUNT];   /* over no proxies */
    static double culled[SCENE_COUNT][FIG3_SERIES][LIMIT_COUNT];
    ex_plot_series series[FIG3_SERIES];
    ex_plot plot;
    char title[128], name[64];
    int i, k;
    for (i = 0; i < SCENE_COUNT; i++) {
        if (s->paper && i == 0) {   /* the crown is not instanced: not the paper's regime */
            for (k = 0; k < FIG3_SERIES; k++) {
                int l;
                for (l = 0; l < LIMIT_COUNT; l++) ratio[i][k][l] = culled[i][k][l] = NAN;
            }
            continue;
        }
        figure3_scene(s, csv, i, limits, &runs);
        for (k = 0; k < FIG3_SERIES; k++) {
            int l;
            for (l = 0; l < LIMIT_COUNT; l++) {
                ratio[i][k][l] = runs.disk[k][l] / runs.disk[k - k % PROXY_KINDS][l];
                culled[i][k][l] = runs.culled[k][l];
            }
        }
        memset(series, 0, sizeof series);
        for (k = 0; k < FIG3_SERIES; k++) {
            series[k].label = labels[k];
            series[k].dashed = k % PROXY_KINDS == 0;
            series[k].x = limits;
            series[k].y = runs.disk[k];
            series[k].count = LIMIT_COUNT;
        }
        memset(&plot, 0, sizeof plot);
        snprintf(title, sizeof title, "Fig. 3: disk bytes read, %s", scene_names[i]);
        plot.title = title;
        plot.x_label = "memory limit (% of geometry bytes)";
        plot.y_label = "disk bytes read (MiB)";
        plot.y_from_zero = 1;
        plot.series = series;
        plot.series_count = FIG3_SERIES;
        snprintf(name, sizeof name, "fig3_%s.svg", scene_names[i]);
        if (!s->paper) write_plot(s, name, &plot);
    }
    close_csv(s, csv, "fig3.csv");
    figure3_table(s, limits, ratio, culled);
}

/* ---- Fig. 4 ---- */

/* The two scenes with closed geometry enough to matter (README "Inner
** proxies"); the crown's solids shadow little of itself under the sun. */
#define FIG4_SCENES 2
#define FIG4_GROUPS (2 * FIG4_SCENES)
static const char *const fig4_scenes[FIG4_SCENES] = {"landscape", "island"};

/* One render at 25 % with shadow rays, inner proxies off or on: its disk
** MiB, and the share of occluded shadow rays they stopped (in %), into
** a row of fig4.csv. */
static void figure4_run(const settings *s, FILE *csv, int i, int scheduler, int inner, double *mib,
                        double *stopped)
{
    static const char *const scheduler_names[2] = {"paper", "batchrt"};
    char extra[12288], stats[4096];
    double occluded, inner_stopped;
    snprintf(stats, sizeof stats, "%s", out_path(s, "fig4_run.json"));
    snprintf(extra, sizeof extra, "--memory 25%% %s --out '%s/run.png' --stats '%s'",
             inner ? "" : "--no-inner", s->out, stats);
    run_render(s, fig4_scenes[i], scheduler, extra);
    occluded = json_number(stats, "occlusion_hits");
    inner_stopped = json_number(stats, "occlusion_inner_stopped");
    *mib = json_number(stats, "disk_bytes_read") / 1048576.0;
    *stopped = occluded > 0 ? 100.0 * inner_stopped / occluded : 0;
    fprintf(csv, "%s,%s,%s,%.0f,%.0f,%.0f,%.0f,%.0f,%.4f,%.0f,%.0f\n", fig4_scenes[i],
            scheduler_names[scheduler], inner ? "outer+inner" : "outer",
            json_number(stats, "disk_bytes_read"), json_number(stats, "batch_loads"),
            json_number(stats, "occlusion_rays"), occluded, inner_stopped, *stopped / 100.0,
            json_number(stats, "occlusion_disk_bytes_read"), json_number(stats, "proxy_bytes"));
    remove(stats);
}

static void figure4(const settings *s)
{
    static const char *const groups[FIG4_GROUPS] = {
        "landscape, paper", "landscape, batchrt", "island, paper", "island, batchrt"};
    static const char *const bars[2] = {"outer proxies", "outer + inner"};
    FILE *csv = open_csv(s, "fig4.csv", "scene,scheduler,proxies,disk_bytes_read,batch_loads,occlusion_rays,"
                                        "occlusion_hits,occlusion_inner_stopped,stopped_share,occlusion_disk_bytes_read,"
                                        "proxy_bytes");
    double mib[2 * FIG4_GROUPS], stopped[2 * FIG4_GROUPS];
    static char rows[FIG4_GROUPS][160];
    static char note_text[FIG4_GROUPS][32];
    const char *notes[2 * FIG4_GROUPS];
    ex_bar_chart chart;
    brt_error err;
    int g, inner;
    for (g = 0; g < FIG4_GROUPS; g++) {
        fprintf(stderr, "Fig. 4: %s's scheduler\n", groups[g]);
        for (inner = 0; inner < 2; inner++)
            figure4_run(s, csv, g / 2, g % 2, inner, &mib[2 * g + inner], &stopped[2 * g + inner]);
        snprintf(note_text[g], sizeof note_text[g], "%.1f %%", stopped[2 * g + 1]);
        notes[2 * g] = NULL;
        notes[2 * g + 1] = note_text[g];
        snprintf(rows[g], sizeof rows[g], "| %s | %.1f | %.1f | %.3f | %.1f %% |\n", groups[g],
                 mib[2 * g], mib[2 * g + 1], mib[2 * g + 1] / mib[2 * g], stopped[2 * g + 1]);
    }
    printf("\nFig. 4 (inner proxies, beyond the paper), disk MiB at 25 %% with shadow rays\n\n"
           "| scene, scheduler | outer | outer + inner | ratio | occluded shadow rays stopped |\n"
           "|---|---:|---:|---:|---:|\n");
    for (g = 0; g < FIG4_GROUPS; g++) fputs(rows[g], stdout);
    close_csv(s, csv, "fig4.csv");
    remove(out_path(s, "run.png"));
    memset(&chart, 0, sizeof chart);
    chart.title = "Fig. 4: disk bytes read at 25 %, outer against outer + inner proxies";
    chart.x_label = "scene, scheduler (above a bar: occluded shadow rays stopped by inner proxies)";
    chart.y_label = "disk bytes read (MiB)";
    chart.groups = groups;
    chart.group_count = FIG4_GROUPS;
    chart.bar_labels = bars;
    chart.bar_count = 2;
    chart.values = mib;
    chart.notes = notes;
    ex_check(prog, ex_bar_write_svg(out_path(s, "fig4.svg"), &chart, &err), &err);
}

int main(int argc, char **argv)
{
    static void (*const figures[FIGURE_COUNT])(const settings *) = {figure1, figure2, figure3, figure4};
    settings s;
    double start = brt_seconds();
    int f;
    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    parse_options(argc, argv, &s);
    remove(out_path(&s, "render.log"));
    for (f = 0; f < FIGURE_COUNT; f++)
        if (s.only == 0 || s.only == f + 1) figures[f](&s);
    fprintf(stderr, "figures: done in %.0f s; PNG, CSV and SVG in %s\n", brt_seconds() - start, s.out);
    return 0;
}
