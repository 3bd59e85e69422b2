/*
** world.c -- the direct mode's world: an instanced scene in memory
** (brt_world), every prototype's BVH and the instances over them in one
** instance set, traced by the same brt_intersect_ray as a batching point of
** instances (batchrt.c), so the two modes give the same bytes.
*/
#include "internal.h"
/* brt_bvh_bounds, which the library uses too. */
#include "testing.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

/* ---- the direct mode's world: an instanced scene in memory ------------ */

struct brt_world {
    brt_bvh *triangles;             /* the world triangles' BVH (prim: file order) */
    brt_bvh **prototypes;
    uint32_t prototype_count;
    instance_set set;               /* instances of non-empty prototypes */
    uint32_t instance_count;        /* every instance streamed */
    uint64_t unique, instanced;
    float lo[3], hi[3];
};

/* Triangles of a stream gathered as corners (9 floats each), checked to
** arrive numbered in order. */
typedef struct corner_list {
    float *corners;
    size_t capacity;
    uint32_t count;
} corner_list;

static brt_result gather_corners(void *user, const float *corners, uint32_t count,
                                 uint32_t first, brt_error *err)
{
    corner_list *l = user;
    float *grown;
    if (first != l->count || count > UINT32_MAX - l->count)
        return brt_fail(err, BRT_EARG, "triangle stream: chunk numbered %u after %u triangles",
                        (unsigned)first, (unsigned)l->count);
    grown = brt_grow(l->corners, &l->capacity, 9 * ((size_t)l->count + count), sizeof *grown);
    if (!grown) return brt_fail(err, BRT_ENOMEM, "out of memory for %u triangles",
                                (unsigned)(l->count + count));
    l->corners = grown;
    memcpy(l->corners + 9 * (size_t)l->count, corners, 9 * (size_t)count * sizeof *corners);
    l->count += count;
    return BRT_OK;
}

/* The BVH of gathered corners (triangle i numbered i). */
static brt_result corners_bvh(const corner_list *l, brt_bvh **out, brt_error *err)
{
    uint32_t *indices = malloc(3 * (size_t)l->count * sizeof *indices + 1), i;
    brt_result rc;
    if (!indices) return brt_fail(err, BRT_ENOMEM, "out of memory for a BVH");
    for (i = 0; i < 3 * l->count; i++) indices[i] = i;
    rc = brt_bvh_build(l->corners, indices, l->count, NULL, out);
    free(indices);
    return rc == BRT_OK ? BRT_OK
                        : brt_fail(err, rc, "cannot build a BVH of %u triangles: %s",
                                   (unsigned)l->count, brt_result_string(rc));
}

/* Runs a triangle stream into a BVH; *count gets its triangles, and lo,
** hi (when not NULL) grow by their exact bounds. */
brt_result brt_stream_bvh(brt_result (*run)(const void *, uint32_t, brt_triangle_fn, void *,
                                               brt_error *),
                             const void *user, uint32_t id, brt_bvh **out, uint32_t *count,
                             float *lo, float *hi, brt_error *err)
{
    corner_list l = {NULL, 0, 0};
    brt_result rc = run(user, id, gather_corners, &l, err);
    size_t i;
    if (rc == BRT_OK) rc = corners_bvh(&l, out, err);
    for (i = 0; lo && i < 3 * (size_t)l.count; i++) brt_bounds_grow(lo, hi, l.corners + 3 * i);
    *count = l.count;
    free(l.corners);
    return rc;
}

static brt_result run_world_stream(const void *user, uint32_t id, brt_triangle_fn emit,
                                   void *emit_user, brt_error *err)
{
    const brt_triangle_source *world = user;
    (void)id;
    return world->run(world->user, emit, emit_user, err);
}

brt_result brt_run_prototype_stream(const void *user, uint32_t id, brt_triangle_fn emit,
                                       void *emit_user, brt_error *err)
{
    const brt_scene_source *source = user;
    return source->prototype(source->user, id, emit, emit_user, err);
}

/* Instances gathered into a world: checked, framed and boxed. */
typedef struct instance_gather {
    brt_world *world;
    const uint32_t *proto_tris;     /* triangles per prototype */
    float *boxes;                   /* 6 per instance of the set */
    float *radii;                   /* 1 per instance of the set */
    size_t id_cap, proto_cap, frame_cap, box_cap, radius_cap;
} instance_gather;

static brt_result gather_instance(instance_gather *g, const brt_instance *in, uint32_t inst,
                                  brt_error *err)
{
    brt_world *w = g->world;
    instance_set *set = &w->set;
    brt_instance_frame frame;
    float olo[3], ohi[3];
    brt_result rc;
    int a;
    if ((rc = brt_instance_admit(in, inst, w->prototype_count, &frame, err)) != BRT_OK) return rc;
    w->instanced += g->proto_tris[in->prototype];
    if (g->proto_tris[in->prototype] == 0) return BRT_OK;   /* never hit */
    if (!(set->ids = brt_grow(set->ids, &g->id_cap, (size_t)set->count + 1, sizeof *set->ids))
        || !(set->prototypes = brt_grow(set->prototypes, &g->proto_cap, (size_t)set->count + 1,
                                        sizeof *set->prototypes))
        || !(set->frames = brt_grow(set->frames, &g->frame_cap, (size_t)set->count + 1,
                                    sizeof *set->frames))
        || !(g->boxes = brt_grow(g->boxes, &g->box_cap, 6 * ((size_t)set->count + 1),
                                 sizeof *g->boxes))
        || !(g->radii = brt_grow(g->radii, &g->radius_cap, (size_t)set->count + 1, sizeof *g->radii)))
        return brt_fail(err, BRT_ENOMEM, "out of memory for %u instances", (unsigned)inst + 1);
    brt_bvh_bounds(w->prototypes[in->prototype], olo, ohi);
    brt_instance_bounds(in, &frame, olo, ohi, g->boxes + 6 * (size_t)set->count,
                        g->boxes + 6 * (size_t)set->count + 3, &g->radii[set->count]);
    for (a = 0; a < 3; a++) {
        if (g->boxes[6 * (size_t)set->count + a] < w->lo[a]) w->lo[a] = g->boxes[6 * (size_t)set->count + a];
        if (g->boxes[6 * (size_t)set->count + 3 + a] > w->hi[a]) w->hi[a] = g->boxes[6 * (size_t)set->count + 3 + a];
    }
    set->ids[set->count] = inst;
    set->prototypes[set->count] = in->prototype;
    set->frames[set->count++] = frame;
    return BRT_OK;
}

static brt_result gather_instances(void *user, const brt_instance *instances, uint32_t count,
                                   uint32_t first, brt_error *err)
{
    instance_gather *g = user;
    uint32_t i;
    if (first != g->world->instance_count || count > UINT32_MAX - first)
        return brt_fail(err, BRT_EARG, "instance stream: chunk numbered %u after %u instances",
                        (unsigned)first, (unsigned)g->world->instance_count);
    for (i = 0; i < count; i++) {
        brt_result rc = gather_instance(g, &instances[i], first + i, err);
        if (rc != BRT_OK) return rc;
        g->world->instance_count++;
    }
    return BRT_OK;
}

static brt_result world_prototypes(brt_world *w, const brt_scene_source *source,
                                   uint32_t *proto_tris, brt_error *err)
{
    uint32_t p;
    for (p = 0; p < w->prototype_count; p++) {
        brt_result rc = brt_stream_bvh(brt_run_prototype_stream, source, p, &w->prototypes[p],
                                   &proto_tris[p], NULL, NULL, err);
        if (rc != BRT_OK) return rc;
        w->unique += proto_tris[p];
    }
    return BRT_OK;
}

static brt_result world_fill(brt_world *w, const brt_scene_source *source, brt_error *err)
{
    instance_gather g;
    uint32_t *proto_tris = calloc((size_t)w->prototype_count + 1, sizeof *proto_tris), n = 0;
    brt_result rc = BRT_OK;
    memset(&g, 0, sizeof g);
    if (!proto_tris) return brt_fail(err, BRT_ENOMEM, "out of memory for the prototypes");
    if (source->world.run)
        rc = brt_stream_bvh(run_world_stream, &source->world, 0, &w->triangles, &n, w->lo, w->hi, err);
    w->unique = w->instanced = n;
    if (rc == BRT_OK) rc = world_prototypes(w, source, proto_tris, err);
    g.world = w;
    g.proto_tris = proto_tris;
    if (rc == BRT_OK && source->instances) rc = source->instances(source->user, gather_instances, &g, err);
    if (rc == BRT_OK && brt_set_build_tree(&w->set, g.boxes) != BRT_OK)
        rc = brt_fail(err, BRT_ENOMEM, "out of memory for the instances' tree");
    if (rc == BRT_OK) brt_set_fit_margin(&w->set, g.boxes, g.radii);
    free(g.boxes);
    free(g.radii);
    free(proto_tris);
    return rc;
}

brt_result brt_world_build(const brt_scene_source *source, brt_world **out, brt_error *err)
{
    brt_world *w = calloc(1, sizeof *w);
    brt_result rc;
    int a;
    *out = NULL;
    if (!w) return brt_fail(err, BRT_ENOMEM, "out of memory for a world");
    for (a = 0; a < 3; a++) { w->lo[a] = INFINITY; w->hi[a] = -INFINITY; }
    w->prototype_count = source->prototype_count;
    w->prototypes = calloc((size_t)w->prototype_count + 1, sizeof *w->prototypes);
    rc = w->prototypes ? world_fill(w, source, err)
                       : brt_fail(err, BRT_ENOMEM, "out of memory for %u prototypes",
                                  (unsigned)w->prototype_count);
    if (rc != BRT_OK) {
        brt_world_free(w);
        return rc;
    }
    *out = w;
    return BRT_OK;
}

void brt_world_free(brt_world *w)
{
    uint32_t p;
    if (!w) return;
    brt_bvh_free(w->triangles);
    for (p = 0; w->prototypes && p < w->prototype_count; p++) brt_bvh_free(w->prototypes[p]);
    free(w->prototypes);
    brt_set_free(&w->set);
    free(w);
}

static geometry world_geometry(const brt_world *w)
{
    geometry g;
    g.triangles = w->triangles;
    g.instances = &w->set;
    g.prototypes = (const brt_bvh *const *)w->prototypes;
    return g;
}

void brt_world_intersect(const brt_world *w, const brt_ray *ray, brt_hit *hit, float normal[3])
{
    const geometry g = world_geometry(w);
    brt_intersect_ray(&g, ray, 0, hit, normal, NULL);
}

int brt_world_occluded(const brt_world *w, const brt_ray *ray)
{
    const geometry g = world_geometry(w);
    brt_hit hit;
    brt_hit_clear(&hit);
    brt_intersect_ray(&g, ray, BRT_TAG_OCCLUSION, &hit, NULL, NULL);
    return hit.t == 0.0f;
}

void brt_world_trace(const brt_world *w, const brt_ray *rays, const uint64_t *tags,
                     size_t count, brt_hit *hits, float *normals, unsigned threads)
{
    const geometry g = world_geometry(w);
    brt_trace_geometry(&g, rays, tags, count, hits, normals, threads);
}

uint32_t brt_world_instance_count(const brt_world *w) { return w->instance_count; }
uint32_t brt_world_prototype_count(const brt_world *w) { return w->prototype_count; }
uint64_t brt_world_unique_triangles(const brt_world *w) { return w->unique; }
uint64_t brt_world_instanced_triangles(const brt_world *w) { return w->instanced; }

void brt_world_bounds(const brt_world *w, float bmin[3], float bmax[3])
{
    memcpy(bmin, w->lo, sizeof w->lo);
    memcpy(bmax, w->hi, sizeof w->hi);
}
