/*
** examples/lib/report.c -- what build/render shows beside its image
** (report.h): the heat map of visits per sample with its colour bar and
** bitmap font, and the table and ratios of --compare.
*/
#include "report.h"

#include "common.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define LEGEND_ROWS 24        /* the heatmap's colour bar and its labels */

/* ---- the heat map ---- */

/* A 5-stop approximation of the "inferno" colour map, for x in [0, 1]. */
static void heat_colour(double x, unsigned char rgb[3])
{
    static const unsigned char stops[5][3] = {
        {0, 0, 4}, {87, 16, 110}, {188, 55, 84}, {249, 142, 9}, {252, 255, 164}};
    double f = fmin(fmax(x, 0.0), 1.0) * 4.0;
    int i = f >= 4.0 ? 3 : (int)f, k;
    f -= i;
    for (k = 0; k < 3; k++)
        rgb[k] = (unsigned char)(stops[i][k] + f * (stops[i + 1][k] - stops[i][k]) + 0.5);
}

/* Digits and the point in a 3x5 bitmap font, rows top first, 3 bits each. */
static int glyph_bits(char c)
{
    static const int digits[10] = {075557, 026227, 071747, 071717, 055711,
                                   074717, 074757, 071111, 075757, 075717};
    return c == '.' ? 000002 : c >= '0' && c <= '9' ? digits[c - '0'] : 0;
}

/* Draws text with 2x2-pixel font dots, its left edge at x (clipped). */
static void draw_text(unsigned char *rgb, int width, int height, int x, int y, const char *text)
{
    int row, col, dy, dx;
    for (; *text; text++, x += 8) {
        int bits = glyph_bits(*text);
        for (row = 0; row < 5; row++)
            for (col = 0; col < 3; col++) {
                if (!(bits >> (3 * (4 - row) + (2 - col)) & 1)) continue;
                for (dy = 0; dy < 2; dy++)
                    for (dx = 0; dx < 2; dx++) {
                        int px = x + 2 * col + dx, py = y + 2 * row + dy;
                        if (px >= 0 && px < width && py >= 0 && py < height)
                            memset(rgb + 3 * ((size_t)py * width + px), 255, 3);
                    }
            }
    }
}

/* The colour bar under the map and its labels 0, max/2 and max. */
static void draw_legend(unsigned char *rgb, int width, int height, double max)
{
    int top = height - LEGEND_ROWS, x, y, i;
    char label[32];
    for (y = top + 2; y < top + 10; y++)
        for (x = 0; x < width; x++)
            heat_colour(width > 1 ? (double)x / (width - 1) : 0, rgb + 3 * ((size_t)y * width + x));
    for (i = 0; i <= 2; i++) {
        int len;
        snprintf(label, sizeof label, "%.1f", max * i / 2.0);
        len = (int)strlen(label) * 8 - 2;
        x = i == 0 ? 2 : i == 1 ? (width - len) / 2 : width - len - 2;
        draw_text(rgb, width, height, x, top + 12, label);
    }
}

brt_result ex_heatmap_write(const char *prog, const char *path, uint32_t width, uint32_t height,
                            const uint64_t *visits, uint32_t spp, double max, brt_error *err)
{
    int w = (int)width, h = (int)height + LEGEND_ROWS;
    size_t i, pixels = (size_t)width * height;
    unsigned char *rgb = calloc(3 * (size_t)w * h, 1);
    brt_result r;
    if (!rgb) ex_die(prog, "out of memory for the heatmap");
    for (i = 0; i < pixels; i++)
        heat_colour((double)visits[i] / spp / max, rgb + 3 * i);
    draw_legend(rgb, w, h, max);
    r = ex_png_write_rgb(path, w, h, rgb, err);
    free(rgb);
    return r;
}

static int compare_u64(const void *a, const void *b)
{
    uint64_t x = *(const uint64_t *)a, y = *(const uint64_t *)b;
    return x < y ? -1 : x > y;
}

double ex_heat_scale(const char *prog, const uint64_t *visits, size_t pixels, uint32_t spp)
{
    uint64_t *sorted = malloc(pixels * sizeof *sorted), top;
    if (!sorted) ex_die(prog, "out of memory for the heatmap");
    memcpy(sorted, visits, pixels * sizeof *sorted);
    qsort(sorted, pixels, sizeof *sorted, compare_u64);
    top = sorted[(size_t)(0.995 * (double)(pixels - 1))];
    free(sorted);
    return top > 0 ? (double)top / spp : 1.0;
}

/* ---- the table of --compare ---- */

void ex_compare_header(void)
{
    printf("| %-22s | %10s | %7s | %10s | %8s | %8s | %8s | %8s | %9s |\n", "run", "disk MiB",
           "loads", "visits/spp", "culled", "time s", "load s", "Mrays/s", "same image");
    printf("|---|---:|---:|---:|---:|---:|---:|---:|---|\n");
}

void ex_compare_row(const char *label, const brt_stats *s, double visits_per_sample,
                    int same_image)
{
    printf("| %-22s | %10.2f | %7llu | %10.2f | %7.1f%% | %8.2f | %8.2f | %8.3f | %9s |\n",
           label, s->disk_bytes_read / 1048576.0, (unsigned long long)s->batch_loads,
           visits_per_sample,
           s->proxy_tests ? 100.0 * s->proxy_culled / s->proxy_tests : 0.0, s->seconds,
           s->load_seconds, s->mrays_per_second, same_image ? "yes" : "NO");
}

void ex_compare_ratios(const brt_stats *without, const brt_stats *with)
{
    printf("proxies: disk bytes x%.2f, loads x%.2f, visits per sample x%.2f, time x%.2f\n",
           (double)with->disk_bytes_read / fmax(1.0, (double)without->disk_bytes_read),
           (double)with->batch_loads / fmax(1.0, (double)without->batch_loads),
           (double)with->visits / fmax(1.0, (double)without->visits),
           with->seconds / without->seconds);
    if (with->proxy_tests == 0)
        printf("(every batching point fits in memory, so the scheduler leaves the proxies\n"
               " alone: they could only put loads off; --paper-scheduler consults them)\n");
}
