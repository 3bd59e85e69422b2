/*
** examples/lib/plot.h -- a small SVG plot writer for `make figures`: one
** panel, a few series of (x, y) points drawn as lines with dots, axes with
** tick labels (linear or logarithmic), a title and a legend; or a grouped
** bar chart on the same panel.  No library: an SVG file is text that any
** browser shows.
*/
#ifndef BRT_EXAMPLES_PLOT_H
#define BRT_EXAMPLES_PLOT_H

#include "common.h"

typedef struct ex_plot_series {
    const char *label;
    const double *x, *y;    /* count points; non-finite ones are skipped */
    size_t count;
    int dashed;             /* draw the line dashed (a "without" series, say) */
} ex_plot_series;

typedef struct ex_plot {
    const char *title, *x_label, *y_label;
    double x_log_base;      /* 0: linear axis; 2 or 10: logarithmic, ticks at powers */
    double y_log_base;
    int y_from_zero;        /* linear y axis starts at 0 whatever the data */
    const ex_plot_series *series;
    size_t series_count;
} ex_plot;

/* The plot as SVG text (malloc'd, NUL-terminated).  BRT_EARG when there is
** no finite point to draw (or a logarithmic axis has no positive one). */
brt_result ex_plot_svg(const ex_plot *plot, char **svg, brt_error *err);

/* The same written to path (atomically). */
brt_result ex_plot_write_svg(const char *path, const ex_plot *plot, brt_error *err);

/* A grouped bar chart: group_count groups side by side along x, each of
** bar_count bars (one colour per bar_labels entry, in the legend), heights
** from 0 on a linear y axis. */
typedef struct ex_bar_chart {
    const char *title, *x_label, *y_label;
    const char *const *groups;       /* group_count labels, under the groups */
    size_t group_count;
    const char *const *bar_labels;   /* bar_count labels, in the legend */
    size_t bar_count;
    const double *values;            /* [group * bar_count + bar]; non-finite ones are skipped */
    const char *const *notes;        /* NULL, or one per value, written above its bar
                                     ** (NULL or "" for none) */
} ex_bar_chart;

/* The chart as SVG text (malloc'd); BRT_EARG when no value is finite. */
brt_result ex_bar_svg(const ex_bar_chart *chart, char **svg, brt_error *err);

/* The same written to path (atomically). */
brt_result ex_bar_write_svg(const char *path, const ex_bar_chart *chart, brt_error *err);

#endif
