/*
** examples/input.c -- a program's geometry input: a mesh file or a pbrt-v4
** scene file, as one scene source (examples/input.h).
*/
#include "input.h"
#include "common.h"

#include <stdio.h>
#include <string.h>

int ex_input_is_pbrt(const char *path)
{
    size_t n = strlen(path);
    return n >= 5 && strcmp(path + n - 5, ".pbrt") == 0;
}

void ex_input_open(const char *prog, const char *path, ex_input *in)
{
    brt_error err;
    memset(in, 0, sizeof *in);
    in->path = path;
    if (!ex_input_is_pbrt(path)) {   /* read when needed, with the reader's messages */
        brt_mesh_file_source(path, &in->source.world);
        return;
    }
    ex_check(prog, ex_pbrt_open(path, &in->pbrt, &err), &err);
    ex_check(prog, brt_scene_source_stamp(path, &in->stamp, &err), &err);
    ex_pbrt_source(in->pbrt, &in->source);
    in->instanced = in->source.prototype_count > 0;
    if (*ex_pbrt_skipped(in->pbrt)) fprintf(stderr, "%s: %s: %s\n", prog, path, ex_pbrt_skipped(in->pbrt));
}

void ex_input_close(ex_input *in)
{
    ex_pbrt_close(in->pbrt);
    in->pbrt = NULL;
}

brt_world *ex_input_world(const char *prog, const ex_input *in)
{
    brt_world *world = NULL;
    brt_error err;
    brt_result r = brt_world_build(&in->source, &world, &err);
    if (r != BRT_OK && ex_interrupted()) ex_die_interrupted(prog);
    ex_check(prog, r, &err);
    return world;
}

brt_scene *ex_input_scene(const char *prog, const ex_input *in, const char *scene_path,
                          const brt_scene_options *opt, int *rebuilt)
{
    brt_scene *scene = NULL;
    brt_error err;
    brt_result r = in->pbrt ? brt_scene_prepare_source(&in->source, in->stamp, scene_path, opt,
                                                       &scene, rebuilt, &err)
                            : brt_scene_prepare(in->path, scene_path, opt, &scene, rebuilt, &err);
    if (r != BRT_OK && ex_interrupted()) ex_die_interrupted(prog);
    ex_check(prog, r, &err);
    return scene;
}

brt_result ex_input_write_hits(const ex_input *in, const char *path, const brt_hit *hits,
                               size_t count, brt_error *err)
{
    return in->instanced ? brt_hits_write_instanced(path, hits, count, err)
                         : brt_hits_write(path, hits, count, err);
}
