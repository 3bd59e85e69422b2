/*
** examples/lib/plot.c -- the SVG plot writer of `make figures` (plot.h): line
** plots and grouped bar charts.
**
** SVG 1.1 in its plainest form: lines, circles, rectangles, text, one <g>
** per series.  The panel is a fixed 760 x 420 canvas: the plot area on the
** left, the legend in a column on the right so that it never hides a point.
** Axis ranges come from the data, widened to "nice" tick steps (1, 2 or 5
** times a power of ten) on a linear axis, or to whole powers of the base on
** a logarithmic one.  A bar chart's x axis is its groups, in equal slots;
** its y axis is linear from 0.
*/
#include "plot.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define CANVAS_W 760
#define CANVAS_H 420
#define AREA_X0 80.0     /* the plot area, in canvas units */
#define AREA_X1 560.0
#define AREA_Y0 40.0
#define AREA_Y1 360.0
#define LEGEND_X 580.0
#define MAX_TICKS 12

static const char *const palette[] = {"#1f77b4", "#d62728", "#2ca02c",
                                      "#ff7f0e", "#9467bd", "#8c564b"};

/* ---- a growing text buffer ---- */

typedef struct text {
    char *data;
    size_t used, capacity;
    int failed;     /* an allocation failed: everything after is dropped */
} text;

static void put(text *t, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;

static void put(text *t, const char *fmt, ...)
{
    va_list ap;
    int n;
    if (t->failed) return;
    va_start(ap, fmt);
    n = vsnprintf(t->data ? t->data + t->used : NULL, t->data ? t->capacity - t->used : 0, fmt, ap);
    va_end(ap);
    if (n < 0) { t->failed = 1; return; }
    if (!t->data || t->used + (size_t)n >= t->capacity) {
        char *grown = brt_grow(t->data, &t->capacity, t->used + (size_t)n + 1, 1);
        if (!grown) { t->failed = 1; return; }
        t->data = grown;
        va_start(ap, fmt);
        vsnprintf(t->data + t->used, t->capacity - t->used, fmt, ap);
        va_end(ap);
    }
    t->used += (size_t)n;
}

/* Text content with the three characters XML reserves escaped. */
static void put_escaped(text *t, const char *s)
{
    for (; s && *s; s++) {
        if (*s == '<') put(t, "&lt;");
        else if (*s == '>') put(t, "&gt;");
        else if (*s == '&') put(t, "&amp;");
        else put(t, "%c", *s);
    }
}

/* ---- axes ---- */

typedef struct axis {
    double lo, hi, log_base;   /* log_base 0: linear */
    double ticks[MAX_TICKS];
    int tick_count;
} axis;

static int usable(double v, double log_base) { return isfinite(v) && (log_base == 0 || v > 0); }

/* 1, 2 or 5 times a power of ten, at least raw. */
static double nice_step(double raw)
{
    double p = pow(10.0, floor(log10(raw))), m = raw / p;
    return (m <= 1 ? 1 : m <= 2 ? 2 : m <= 5 ? 5 : 10) * p;
}

static void axis_linear(axis *a, int from_zero)
{
    double step;
    int i;
    if (from_zero && a->lo > 0) a->lo = 0;
    if (a->hi <= a->lo) { a->hi = a->lo + fmax(1.0, fabs(a->lo)); }
    step = nice_step((a->hi - a->lo) / 5.0);
    a->lo = floor(a->lo / step) * step;
    a->hi = ceil(a->hi / step) * step;
    for (i = 0; i < MAX_TICKS && a->lo + i * step <= a->hi * (1 + 1e-12) + 1e-300; i++)
        a->ticks[i] = a->lo + i * step;
    a->tick_count = i;
}

/* Whole powers of the base around the data; every power is a tick while
** they fit, else every second, third, ... one. */
static void axis_log(axis *a)
{
    double e_lo = floor(log(a->lo) / log(a->log_base) + 1e-9);
    double e_hi = ceil(log(a->hi) / log(a->log_base) - 1e-9), e;
    int every, i = 0;
    if (e_hi <= e_lo) e_hi = e_lo + 1;
    every = (int)ceil((e_hi - e_lo + 1) / MAX_TICKS);
    a->lo = pow(a->log_base, e_lo);
    a->hi = pow(a->log_base, e_hi);
    for (e = e_lo; e <= e_hi && i < MAX_TICKS; e += every) a->ticks[i++] = pow(a->log_base, e);
    a->tick_count = i;
}

/* Range of the usable values of one coordinate over all series. */
static int axis_fit(axis *a, const ex_plot *plot, int use_y, double log_base, int from_zero)
{
    size_t s, i;
    a->lo = INFINITY;
    a->hi = -INFINITY;
    a->log_base = log_base;
    for (s = 0; s < plot->series_count; s++)
        for (i = 0; i < plot->series[s].count; i++) {
            double v = use_y ? plot->series[s].y[i] : plot->series[s].x[i];
            double other = use_y ? plot->series[s].x[i] : plot->series[s].y[i];
            double other_base = use_y ? plot->x_log_base : plot->y_log_base;
            if (!usable(v, log_base) || !usable(other, other_base)) continue;
            a->lo = fmin(a->lo, v);
            a->hi = fmax(a->hi, v);
        }
    if (!(a->lo <= a->hi)) return 0;
    if (log_base > 0) axis_log(a);
    else axis_linear(a, from_zero);
    return 1;
}

/* Where v falls between lo and hi, 0..1. */
static double axis_fraction(const axis *a, double v)
{
    if (a->log_base > 0) return (log(v) - log(a->lo)) / (log(a->hi) - log(a->lo));
    return (v - a->lo) / (a->hi - a->lo);
}

static double to_x(const axis *a, double v) { return AREA_X0 + axis_fraction(a, v) * (AREA_X1 - AREA_X0); }
static double to_y(const axis *a, double v) { return AREA_Y1 - axis_fraction(a, v) * (AREA_Y1 - AREA_Y0); }

/* ---- drawing ---- */

/* The plot area's frame, the y axis's ticks, the title and the axis labels. */
static void draw_frame(text *t, const char *title, const char *x_label, const char *y_label, const axis *ay)
{
    int i;
    put(t, "<rect x=\"%.1f\" y=\"%.1f\" width=\"%.1f\" height=\"%.1f\" fill=\"none\" stroke=\"#000\"/>\n",
        AREA_X0, AREA_Y0, AREA_X1 - AREA_X0, AREA_Y1 - AREA_Y0);
    for (i = 0; i < ay->tick_count; i++) {
        double y = to_y(ay, ay->ticks[i]);
        put(t, "<line x1=\"%.1f\" y1=\"%.1f\" x2=\"%.1f\" y2=\"%.1f\" stroke=\"#ddd\"/>\n", AREA_X0, y, AREA_X1, y);
        put(t, "<text x=\"%.1f\" y=\"%.1f\" text-anchor=\"end\">%g</text>\n", AREA_X0 - 6, y + 4, ay->ticks[i]);
    }
    put(t, "<text x=\"%.1f\" y=\"24\" text-anchor=\"middle\" font-weight=\"bold\">", (AREA_X0 + AREA_X1) / 2);
    put_escaped(t, title);
    put(t, "</text>\n<text x=\"%.1f\" y=\"%.1f\" text-anchor=\"middle\">", (AREA_X0 + AREA_X1) / 2, AREA_Y1 + 42);
    put_escaped(t, x_label);
    put(t, "</text>\n<text transform=\"translate(18 %.1f) rotate(-90)\" text-anchor=\"middle\">",
        (AREA_Y0 + AREA_Y1) / 2);
    put_escaped(t, y_label);
    put(t, "</text>\n");
}

static void draw_axes(text *t, const ex_plot *plot, const axis *ax, const axis *ay)
{
    int i;
    draw_frame(t, plot->title, plot->x_label, plot->y_label, ay);
    for (i = 0; i < ax->tick_count; i++) {
        double x = to_x(ax, ax->ticks[i]);
        put(t, "<line x1=\"%.1f\" y1=\"%.1f\" x2=\"%.1f\" y2=\"%.1f\" stroke=\"#ddd\"/>\n", x, AREA_Y0, x, AREA_Y1);
        put(t, "<text x=\"%.1f\" y=\"%.1f\" text-anchor=\"middle\">%g</text>\n", x, AREA_Y1 + 18, ax->ticks[i]);
    }
}

static void draw_series(text *t, const ex_plot *plot, size_t s, const axis *ax, const axis *ay)
{
    const ex_plot_series *series = &plot->series[s];
    const char *colour = palette[s % (sizeof palette / sizeof palette[0])];
    double legend_y = AREA_Y0 + 10 + 22.0 * (double)s;
    size_t i;
    put(t, "<g stroke=\"%s\" fill=\"%s\">\n<polyline fill=\"none\" stroke-width=\"2\"%s points=\"",
        colour, colour, series->dashed ? " stroke-dasharray=\"6,4\"" : "");
    for (i = 0; i < series->count; i++)
        if (usable(series->x[i], plot->x_log_base) && usable(series->y[i], plot->y_log_base))
            put(t, "%.1f,%.1f ", to_x(ax, series->x[i]), to_y(ay, series->y[i]));
    put(t, "\"/>\n");
    for (i = 0; i < series->count; i++)
        if (usable(series->x[i], plot->x_log_base) && usable(series->y[i], plot->y_log_base))
            put(t, "<circle cx=\"%.1f\" cy=\"%.1f\" r=\"3\"/>\n", to_x(ax, series->x[i]),
                to_y(ay, series->y[i]));
    put(t, "<line x1=\"%.1f\" y1=\"%.1f\" x2=\"%.1f\" y2=\"%.1f\" stroke-width=\"2\"%s/>\n", LEGEND_X,
        legend_y, LEGEND_X + 28, legend_y, series->dashed ? " stroke-dasharray=\"6,4\"" : "");
    put(t, "<text x=\"%.1f\" y=\"%.1f\" stroke=\"none\" fill=\"#000\">", LEGEND_X + 36, legend_y + 4);
    put_escaped(t, series->label);
    put(t, "</text>\n</g>\n");
}

/* The SVG header and a white background. */
static void svg_begin(text *t)
{
    put(t, "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n"
           "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"%d\" height=\"%d\" "
           "viewBox=\"0 0 %d %d\" font-family=\"sans-serif\" font-size=\"13\">\n"
           "<rect width=\"100%%\" height=\"100%%\" fill=\"#fff\"/>\n",
        CANVAS_W, CANVAS_H, CANVAS_W, CANVAS_H);
}

/* Closes the SVG and hands its text to *svg, or fails if memory ran out. */
static brt_result svg_end(text *t, const char *title, char **svg, brt_error *err)
{
    put(t, "</svg>\n");
    if (t->failed) {
        free(t->data);
        return brt_fail(err, BRT_ENOMEM, "plot '%s': out of memory", title ? title : "");
    }
    *svg = t->data;
    return BRT_OK;
}

/* Writes the SVG text that a maker returned (with r) to path, atomically. */
static brt_result write_svg(const char *path, char *svg, brt_result r, brt_error *err)
{
    if (r != BRT_OK) return r;
    r = brt_write_file_atomic(path, svg, strlen(svg), err);
    free(svg);
    return r;
}

brt_result ex_plot_svg(const ex_plot *plot, char **svg, brt_error *err)
{
    text t = {NULL, 0, 0, 0};
    axis ax, ay;
    size_t s;
    *svg = NULL;
    if (!axis_fit(&ax, plot, 0, plot->x_log_base, 0) || !axis_fit(&ay, plot, 1, plot->y_log_base,
                                                                  plot->y_from_zero))
        return brt_fail(err, BRT_EARG, "plot '%s': no point to draw", plot->title ? plot->title : "");
    svg_begin(&t);
    draw_axes(&t, plot, &ax, &ay);
    for (s = 0; s < plot->series_count; s++) draw_series(&t, plot, s, &ax, &ay);
    return svg_end(&t, plot->title, svg, err);
}

brt_result ex_plot_write_svg(const char *path, const ex_plot *plot, brt_error *err)
{
    char *svg;
    brt_result r = ex_plot_svg(plot, &svg, err);
    return write_svg(path, svg, r, err);
}

/* ---- bar charts ---- */

/* Fraction of a group's slot that its bars fill; the rest separates groups. */
#define BAR_FILL 0.7

/* The y axis: 0 and every finite value, widened to nice steps. */
static int bar_axis(axis *a, const ex_bar_chart *chart)
{
    size_t i, n = chart->group_count * chart->bar_count;
    int any = 0;
    a->lo = a->hi = 0;
    a->log_base = 0;
    for (i = 0; i < n; i++)
        if (isfinite(chart->values[i])) {
            a->lo = fmin(a->lo, chart->values[i]);
            a->hi = fmax(a->hi, chart->values[i]);
            any = 1;
        }
    if (any) axis_linear(a, 1);
    return any;
}

/* Group g's label, under the middle of its slot (a size smaller than the
** tick labels: a slot of four groups is 120 units, about 20 characters). */
static void draw_group_label(text *t, const ex_bar_chart *chart, size_t g)
{
    double slot = (AREA_X1 - AREA_X0) / (double)chart->group_count;
    put(t, "<text x=\"%.1f\" y=\"%.1f\" text-anchor=\"middle\" font-size=\"11\">",
        AREA_X0 + slot * ((double)g + 0.5),
        AREA_Y1 + 18);
    put_escaped(t, chart->groups[g]);
    put(t, "</text>\n");
}

/* Bar b of every group, in its colour, with the notes above and a legend
** entry.  A bar spans 0..value, so a negative one hangs below the 0 line. */
static void draw_bars(text *t, const ex_bar_chart *chart, size_t b, const axis *ay)
{
    const char *colour = palette[b % (sizeof palette / sizeof palette[0])];
    double slot = (AREA_X1 - AREA_X0) / (double)chart->group_count;
    double width = slot * BAR_FILL / (double)chart->bar_count;
    double legend_y = AREA_Y0 + 10 + 22.0 * (double)b;
    size_t g;
    put(t, "<g fill=\"%s\">\n", colour);
    for (g = 0; g < chart->group_count; g++) {
        size_t k = g * chart->bar_count + b;
        double v = chart->values[k], x = AREA_X0 + slot * ((double)g + (1 - BAR_FILL) / 2) + width * (double)b;
        double top, bottom;
        if (!isfinite(v)) continue;
        top = to_y(ay, fmax(v, 0));
        bottom = to_y(ay, fmin(v, 0));
        put(t, "<rect class=\"bar\" x=\"%.1f\" y=\"%.1f\" width=\"%.1f\" height=\"%.1f\"/>\n", x, top, width,
            bottom - top);
        if (chart->notes && chart->notes[k] && chart->notes[k][0]) {
            put(t, "<text x=\"%.1f\" y=\"%.1f\" text-anchor=\"middle\" fill=\"#000\">", x + width / 2, top - 5);
            put_escaped(t, chart->notes[k]);
            put(t, "</text>\n");
        }
    }
    put(t, "<rect x=\"%.1f\" y=\"%.1f\" width=\"28\" height=\"10\"/>\n", LEGEND_X, legend_y - 5);
    put(t, "<text x=\"%.1f\" y=\"%.1f\" fill=\"#000\">", LEGEND_X + 36, legend_y + 4);
    put_escaped(t, chart->bar_labels[b]);
    put(t, "</text>\n</g>\n");
}

brt_result ex_bar_svg(const ex_bar_chart *chart, char **svg, brt_error *err)
{
    text t = {NULL, 0, 0, 0};
    axis ay;
    size_t i;
    *svg = NULL;
    if (chart->group_count == 0 || chart->bar_count == 0 || !bar_axis(&ay, chart))
        return brt_fail(err, BRT_EARG, "plot '%s': no bar to draw", chart->title ? chart->title : "");
    svg_begin(&t);
    draw_frame(&t, chart->title, chart->x_label, chart->y_label, &ay);
    for (i = 0; i < chart->group_count; i++) draw_group_label(&t, chart, i);
    for (i = 0; i < chart->bar_count; i++) draw_bars(&t, chart, i, &ay);
    return svg_end(&t, chart->title, svg, err);
}

brt_result ex_bar_write_svg(const char *path, const ex_bar_chart *chart, brt_error *err)
{
    char *svg;
    brt_result r = ex_bar_svg(chart, &svg, err);
    return write_svg(path, svg, r, err);
}
