/*
** tests/test_thresholds.c -- the constants that split work, crossed for
** real (issue 38: a chunk, a read or a table that no test input reaches
** hides every slip in the code that joins its pieces).
**
** Each test builds an input just past the split (and, where cheap, exactly
** at it) and compares the answer with a reference that does not split:
** the direct mode's BVH, or the documented limit of the format.
**   - a blob is read from the scene file in pieces of CACHE_READ_CHUNK
**     (8 MiB, batchrt.c): one batching point of a larger blob;
**   - a PLY header holds at most 16 elements of 64 properties each
**     (PLY_MAX_ELEMENTS, PLY_MAX_PROPERTIES): 16 and 64 are read, 17 and
**     65 refused with the header's line.
*/
#include "test.h"
#include "util.h"

#include <stdlib.h>
#include <string.h>

/* One batching point whose blob is larger than one read of the cache: the
** pieces are joined at the right offsets when every hit is the direct
** mode's (a slip in the offset of the second piece fails the blob's
** checksum; one in its length leaves bytes unread). */
static void test_blob_past_one_read(void)
{
    const uint32_t triangles = 300000;     /* about 14 MB of blob: two reads and a part */
    const size_t count = 20000;
    tu_scene s;
    brt_scene *scene;
    brt_bvh *bvh = NULL;
    brt_ray *rays;
    brt_hit *direct, *batched;
    brt_trace_options opt;
    brt_stats stats;
    brt_error err;
    float lo[3], hi[3];
    uint64_t st = test_seed() + 38;
    size_t i, differ = 0;
    memset(&s, 0, sizeof s);
    tu_random_soup(&s, &st, triangles, 0.01f);
    scene = tu_build_scene(&s, triangles, 16, 1, tu_scratch("big-blob.brs"));
    rays = malloc(count * sizeof *rays);
    direct = malloc(count * sizeof *direct);
    batched = malloc(count * sizeof *batched);
    if (!scene || !rays || !direct || !batched || brt_bvh_build(s.pos, s.idx, s.tcount, NULL, &bvh) != BRT_OK) {
        EXPECT(0, "setup failed");
        goto done;
    }
    tu_scene_bounds(&s, lo, hi);
    for (i = 0; i < count; i++) {
        tu_make_ray(&s, lo, hi, (int)(i % TU_RAY_KINDS), &st, &rays[i]);
        brt_hit_clear(&direct[i]);
        brt_bvh_intersect(bvh, &rays[i], &direct[i]);
    }
    memset(&opt, 0, sizeof opt);
    opt.threads = 1;
    if (brt_scene_trace(scene, &opt, rays, count, batched, &stats, &err) != BRT_OK) {
        EXPECT(0, "trace: %s", err.message);
        goto done;
    }
    EXPECT(stats.batching_points == 1 && stats.geometry_bytes > ((uint64_t)8 << 20),
           "%llu points, %llu geometry bytes: not one blob past 8 MiB", (unsigned long long)stats.batching_points,
           (unsigned long long)stats.geometry_bytes);
    for (i = 0; i < count; i++) differ += memcmp(&direct[i], &batched[i], sizeof *batched) != 0;
    EXPECT(differ == 0, "%zu of %zu hits differ from the direct mode's", differ, count);
done:
    if (scene) brt_scene_close(scene);
    brt_bvh_free(bvh);
    free(rays);
    free(direct);
    free(batched);
    tu_scene_free(&s);
}

/* A PLY header of `elements` elements (the first the vertices, the last
** the faces, others empty in between), the vertex element with
** `properties` properties (x y z first, then extras): one triangle. */
static char *ply_header_text(int elements, int properties)
{
    size_t cap = 8192, used = 0;
    char *t = malloc(cap);
    int e, p;
    if (!t) return NULL;
    used += (size_t)snprintf(t + used, cap - used, "ply\nformat ascii 1.0\nelement vertex 3\n");
    for (p = 0; p < properties; p++)
        used += (size_t)snprintf(t + used, cap - used, p < 3 ? "property float %c\n" : "property float extra%d\n",
                                 p < 3 ? "xyz"[p] : p);
    for (e = 2; e < elements; e++) used += (size_t)snprintf(t + used, cap - used, "element other%d 0\nproperty int a\n", e);
    used += (size_t)snprintf(t + used, cap - used, "element face 1\nproperty list uchar int vertex_indices\nend_header\n");
    for (e = 0; e < 3; e++) {
        for (p = 0; p < properties; p++)
            used += (size_t)snprintf(t + used, cap - used, "%s%d", p ? " " : "", p < 3 ? (p == e - 1) : 7);
        used += (size_t)snprintf(t + used, cap - used, "\n");
    }
    snprintf(t + used, cap - used, "3 0 1 2\n");
    return t;
}

/* The header line of the first element past the limit: "ply", "format",
** the vertex element and its properties, then two lines per element. */
static void test_ply_header_limits(void)
{
    static const struct { int elements, properties, ok; const char *where, *reason; } cases[] = {
        {16, 3, 1, NULL, NULL},
        {17, 3, 0, ":37:", "more than 16 elements"},
        {2, 64, 1, NULL, NULL},
        {2, 65, 0, ":68:", "more than 64 properties"},
    };
    size_t i;
    for (i = 0; i < sizeof cases / sizeof *cases; i++) {
        char *text = ply_header_text(cases[i].elements, cases[i].properties);
        brt_mesh mesh;
        brt_error err;
        brt_result r;
        CHECK(text, "out of memory");
        r = brt_mesh_parse_ply("limits.ply", text, strlen(text), &mesh, &err);
        if (cases[i].ok) {
            EXPECT(r == BRT_OK && mesh.triangle_count == 1, "%d elements of %d properties: %s",
                   cases[i].elements, cases[i].properties, r == BRT_OK ? "not one triangle" : err.message);
            if (r == BRT_OK) brt_mesh_free(&mesh);
        } else
            EXPECT(r == BRT_EPARSE && strstr(err.message, cases[i].where) && strstr(err.message, cases[i].reason),
                   "%d elements of %d properties: '%s', want '%s' and '%s'", cases[i].elements,
                   cases[i].properties, r == BRT_OK ? "accepted" : err.message, cases[i].where, cases[i].reason);
        free(text);
    }
}

void suite_thresholds(void)
{
    test_run("thresholds: a blob larger than one cache read (8 MiB) == direct", test_blob_past_one_read);
    test_run("thresholds: PLY headers of 16 elements and 64 properties, one past each", test_ply_header_limits);
}
