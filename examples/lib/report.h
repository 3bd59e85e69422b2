/*
** examples/lib/report.h -- what build/render shows beside its image: the
** heat map of batching points visited per sample (the paper's Fig. 1),
** with its colour bar and a 3x5 bitmap font for the bar's labels, and the
** table and ratios of --compare.  render.c keeps the path tracer itself.
*/
#ifndef BRT_EXAMPLES_REPORT_H
#define BRT_EXAMPLES_REPORT_H

#include "batchrt.h"

#include <stddef.h>
#include <stdint.h>

/* The top of the heat map's colour scale: the 99.5th percentile of the
** pixels' visits per sample (visits[i] / spp), so that a few extreme
** pixels (rays grazing many boxes) do not darken the rest; pixels above
** it get the top colour.  1 when that is 0.  Dies (as prog) without memory. */
double ex_heat_scale(const char *prog, const uint64_t *visits, size_t pixels, uint32_t spp);

/* Writes the heat map of a width x height image as a PNG: pixel i coloured
** by visits[i] / spp / max ("inferno"), and below it a colour bar labelled
** 0, max/2 and max.  Dies (as prog) without memory; a failed write is the
** result, with err set. */
brt_result ex_heatmap_write(const char *prog, const char *path, uint32_t width, uint32_t height,
                            const uint64_t *visits, uint32_t spp, double max, brt_error *err);

/* --compare's Markdown table: the header, then one row a run (its label,
** statistics, visits per sample, and whether its image has the bytes of
** the first run's). */
void ex_compare_header(void);
void ex_compare_row(const char *label, const brt_stats *s, double visits_per_sample,
                    int same_image);

/* The line of ratios, proxies on against off, and a note when the proxies
** were never consulted. */
void ex_compare_ratios(const brt_stats *without, const brt_stats *with);

#endif
