/*
** examples/lib/tracer.c -- the command line the three tracers share
** (tracer.h): the options of build/trace, build/mpi_trace and
** build/embree_trace, parsed once.
*/
#include "tracer.h"

#include "common.h"

#include <string.h>

void ex_tracer_defaults(ex_tracer_options *o)
{
    memset(o, 0, sizeof *o);
    o->res = 128;
    o->memory = (uint64_t)1 << 30;
}

/* Takes argv[*i] when it is an option of every tracer. */
static int common_option(const char *prog, int argc, char **argv, int *i, ex_tracer_options *o)
{
    const char *a = argv[*i];
    if (strcmp(a, "--occlusion") == 0) o->occlusion = 1;
    else if (strcmp(a, "--verbose") == 0) o->verbose = 1;
    else if (strcmp(a, "--stats") == 0) o->stats = ex_option_value(prog, argc, argv, i);
    else return 0;
    return 1;
}

/* Takes argv[*i] when it is one of the batched settings. */
static int batched_option(const ex_tracer_command *c, int argc, char **argv, int *i,
                          ex_tracer_options *o)
{
    const char *prog = c->prog, *a = argv[*i];
    if (strcmp(a, "--no-proxy") == 0) o->no_proxy = 1;
    else if (strcmp(a, "--paper-scheduler") == 0) o->paper_scheduler = 1;
    else if (strcmp(a, "--no-clip") == 0) o->no_clip = 1;
    else if (strcmp(a, "--no-order") == 0) o->no_order = 1;
    else if (strcmp(a, "--proxies-in-core") == 0) o->proxies_in_core = 1;
    else if (strcmp(a, "--point-tris") == 0)
        o->point_tris = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, i), 1, UINT32_MAX);
    else if (strcmp(a, "--proxy-res") == 0)
        o->res = ex_parse_resolution(prog, a, ex_option_value(prog, argc, argv, i));
    else if (strcmp(a, "--memory") == 0) {
        o->memory = ex_parse_size(prog, a, ex_option_value(prog, argc, argv, i));
        o->memory_given = 1;
    }
    else if (strcmp(a, "--rays-in-flight") == 0)
        o->rays_in_flight = ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, i), 1,
                                         c->max_rays_in_flight);
    else if (strcmp(a, "--threads") == 0)
        o->threads = (unsigned)ex_parse_u64(prog, a, ex_option_value(prog, argc, argv, i), 0,
                                            BRT_MAX_THREADS);
    else if (strcmp(a, "--scene") == 0) o->scene = ex_option_value(prog, argc, argv, i);
    else return 0;
    return 1;
}

void ex_tracer_parse(const ex_tracer_command *c, int argc, char **argv, ex_tracer_options *o)
{
    const char **positional[3];
    int i, npos = 0;
    positional[0] = &o->input;
    positional[1] = &o->rays;
    positional[2] = &o->hits;
    for (i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (common_option(c->prog, argc, argv, &i, o)) continue;
        if (c->batched && batched_option(c, argc, argv, &i, o)) continue;
        if (c->own(c->user, argc, argv, &i)) continue;
        if (a[0] == '-' && a[1] != 0) ex_unknown_option(c->prog, a);
        if (npos == 3) ex_die(c->prog, "unexpected argument '%s' (see --help)", a);
        *positional[npos++] = a;
    }
    if (npos < 3)
        ex_die(c->prog, "expected %s, got %d file name%s (see --help)", c->files, npos,
               npos == 1 ? "" : "s");
}

void ex_tracer_point_size(const ex_input *in, ex_tracer_options *o)
{
    if (o->point_tris == 0) o->point_tris = ex_default_point_tris(ex_input_triangles(in), o->memory, 0);
}

const char *ex_tracer_scene_path(const char *prog, const ex_tracer_options *o, char *path,
                                 size_t size)
{
    if (o->scene) return o->scene;
    ex_default_scene_path(prog, o->input, (uint32_t)o->point_tris, (uint32_t)o->res, path, size);
    return path;
}

void ex_tracer_trace_options(const ex_tracer_options *o, brt_trace_options *t)
{
    t->memory_limit = o->memory;
    t->no_proxy = o->no_proxy;
    t->paper_scheduler = o->paper_scheduler;
    t->no_clip = o->no_clip;
    t->no_order = o->no_order;
    t->proxies_in_core = o->proxies_in_core;
    t->threads = o->threads;
    t->rays_in_flight = (uint32_t)o->rays_in_flight;
}
