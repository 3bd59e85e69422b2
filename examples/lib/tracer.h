/*
** examples/lib/tracer.h -- the command line the three tracers share
** (build/trace, build/mpi_trace, build/embree_trace): three file names, the
** options each of them takes, and the batched mode's settings, parsed in
** one place.  Each program hands its own options to the parser through a
** callback, and keeps its own usage text.
*/
#ifndef BRT_EXAMPLES_TRACER_H
#define BRT_EXAMPLES_TRACER_H

#include "batchrt.h"
#include "input.h"

#include <stddef.h>
#include <stdint.h>

typedef struct ex_tracer_options {
    const char *input, *rays, *hits; /* the three positional arguments */
    int occlusion;                   /* --occlusion: one byte per ray */
    const char *stats;               /* --stats FILE.json, or NULL */
    int verbose;                     /* --verbose: summary line even when not a tty */
    /* The batched settings (ex_tracer_command.batched): */
    uint64_t point_tris;             /* --point-tris; 0: not given (ex_tracer_point_size) */
    uint64_t res;                    /* --proxy-res: proxy resolution, a power of two */
    uint64_t memory;                 /* --memory: geometry-cache budget in bytes */
    int memory_given;                /* --memory was on the command line */
    uint64_t rays_in_flight;         /* --rays-in-flight; 0: the library's default */
    int no_proxy;                    /* --no-proxy: batched without voxel proxies */
    int paper_scheduler;             /* --paper-scheduler (brt_trace_options) */
    int no_clip, no_order;           /* --no-clip, --no-order (layers 10, 11) */
    int proxies_in_core;             /* --proxies-in-core (brt_trace_options) */
    const char *scene;               /* --scene FILE, or NULL: the default path */
    unsigned threads;                /* --threads; 0: all cores */
} ex_tracer_options;

/* One program's command line. */
typedef struct ex_tracer_command {
    const char *prog;                /* for messages, e.g. "trace" */
    const char *files;               /* the positional arguments' names, e.g. "MESH RAYS HITS" */
    int batched;                     /* takes the batched settings */
    uint64_t max_rays_in_flight;     /* --rays-in-flight's upper bound */
    /* The program's own options: takes argv[*i] (a value through
    ** ex_option_value) and returns 1, or returns 0 when it is not one of
    ** them.  Asked before an option is called unknown. */
    int (*own)(void *user, int argc, char **argv, int *i);
    void *user;
} ex_tracer_command;

/* Zeroes o, then the defaults: --proxy-res 128, --memory 1G (--point-tris:
** ex_tracer_point_size). */
void ex_tracer_defaults(ex_tracer_options *o);

/* Parses argv into o (which holds the defaults) and the program's own
** options; dies naming the problem, e.g. "trace: unknown option '--x' (see
** --help)" or "trace: expected MESH RAYS HITS, got 2 file names (see --help)". */
void ex_tracer_parse(const ex_tracer_command *c, int argc, char **argv, ex_tracer_options *o);

/* --point-tris when not given: ex_default_point_tris of the input's
** unique triangles (ex_input_triangles) and --memory (its default too: a
** limit).  Called before ex_tracer_scene_path, whose default file name
** holds the size. */
void ex_tracer_point_size(const ex_input *in, ex_tracer_options *o);

/* The scene file of the batched mode: --scene, else the default path of
** the input and its settings (ex_default_scene_path), written to path. */
const char *ex_tracer_scene_path(const char *prog, const ex_tracer_options *o, char *path,
                                 size_t size);

/* The batched settings that go to the scheduler: memory limit, proxies,
** scheduler, threads and rays in flight. */
void ex_tracer_trace_options(const ex_tracer_options *o, brt_trace_options *t);

#endif
