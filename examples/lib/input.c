/*
** examples/lib/input.c -- a program's geometry input: a mesh file or a pbrt-v4
** scene file, as one scene source (examples/lib/input.h).
*/
#include "input.h"
#include "common.h"

#include <stdio.h>
#include <stdlib.h>
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
    ex_check(prog, brt_world_build(&in->source, &world, &err), &err);
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
    ex_check(prog, r, &err);
    return scene;
}

brt_result ex_input_write_hits(const ex_input *in, const char *path, const brt_hit *hits,
                               size_t count, brt_error *err)
{
    return in->instanced ? brt_hits_write_instanced(path, hits, count, err)
                         : brt_hits_write(path, hits, count, err);
}

uint64_t ex_input_triangles(const ex_input *in)
{
    return in->pbrt ? ex_pbrt_triangles(in->pbrt) : ex_mesh_file_triangles(in->path);
}

/* ---- flattening (the analysis programs) ---- */

typedef struct flattener {
    const brt_scene_source *source;
    ex_corners *prototypes;         /* each prototype's corners, gathered once */
    ex_corners out;                 /* the flattened triangles */
} flattener;

static brt_result flatten_instances(void *user, const brt_instance *in, uint32_t count,
                                    uint32_t first, brt_error *err)
{
    flattener *f = user;
    uint32_t i;
    size_t t;
    int c, a;
    for (i = 0; i < count; i++) {
        const ex_corners *p;
        if (in[i].prototype >= f->source->prototype_count)
            return brt_fail(err, BRT_EARG, "instance %u: prototype %u out of range",
                            (unsigned)(first + i), (unsigned)in[i].prototype);
        p = &f->prototypes[in[i].prototype];
        for (t = 0; t < p->count; t++) {
            float tri[9];
            brt_result r;
            for (c = 0; c < 3; c++)
                for (a = 0; a < 3; a++) {
                    const float *v = p->corners + 9 * t + 3 * c, *m = in[i].xform + 4 * a;
                    tri[3 * c + a] = (float)((double)m[0] * v[0] + (double)m[1] * v[1] +
                                             (double)m[2] * v[2] + m[3]);
                }
            if ((r = ex_corners_append(&f->out, tri, 1, 0, err)) != BRT_OK) return r;
        }
    }
    return BRT_OK;
}

void ex_input_load_mesh(const char *prog, const char *path, brt_mesh *mesh)
{
    ex_input in;
    flattener f;
    brt_error err;
    uint32_t p;
    size_t i;
    memset(mesh, 0, sizeof *mesh);
    if (!ex_input_is_pbrt(path)) {
        ex_check(prog, brt_mesh_load(path, mesh, &err), &err);
        return;
    }
    ex_input_open(prog, path, &in);
    memset(&f, 0, sizeof f);
    f.source = &in.source;
    f.prototypes = calloc((size_t)in.source.prototype_count + 1, sizeof *f.prototypes);
    if (!f.prototypes) ex_die(prog, "out of memory");
    if (in.source.world.run)
        ex_check(prog, in.source.world.run(in.source.world.user, ex_corners_append, &f.out, &err), &err);
    for (p = 0; p < in.source.prototype_count; p++)
        ex_check(prog, in.source.prototype(in.source.user, p, ex_corners_append, &f.prototypes[p], &err),
                 &err);
    if (in.source.instances)
        ex_check(prog, in.source.instances(in.source.user, flatten_instances, &f, &err), &err);
    if (f.out.count == 0 || f.out.count > 0xFFFFFFFEu / 3)
        ex_die(prog, "%s: %s", path, f.out.count ? "too many triangles to flatten" : "no triangles");
    mesh->positions = f.out.corners;
    mesh->triangle_count = (uint32_t)f.out.count;
    mesh->vertex_count = 3 * mesh->triangle_count;
    mesh->indices = malloc(3 * f.out.count * sizeof *mesh->indices);
    if (!mesh->indices) ex_die(prog, "out of memory for %lu triangles", (unsigned long)f.out.count);
    for (i = 0; i < 3 * f.out.count; i++) mesh->indices[i] = (uint32_t)i;
    for (p = 0; p < in.source.prototype_count; p++) free(f.prototypes[p].corners);
    free(f.prototypes);
    ex_input_close(&in);
}

uint64_t ex_scene_geometry_bytes(const char *prog, brt_scene *scene)
{
    brt_trace_options topt;
    brt_stats stats;
    brt_error err;
    memset(&topt, 0, sizeof topt);
    topt.rays_in_flight = 1;
    ex_check(prog, brt_scene_trace(scene, &topt, NULL, 0, NULL, &stats, &err), &err);
    return stats.geometry_bytes;
}
