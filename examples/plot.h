/*
** examples/plot.h -- a small SVG line-plot writer for `make figures`: one
** panel, a few series of (x, y) points drawn as lines with dots, axes with
** tick labels (linear or logarithmic), a title and a legend.  No library:
** an SVG file is text that any browser shows.
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

#endif
