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
**     65 refused with the header's line;
**   - the built-in instanced scenes stream instances in chunks of
**     EX_INSTANCE_CHUNK (4096): every instance of a scene of several
**     chunks is the one its number makes, and no two are alike;
**   - a PNG's pixels go in stored deflate blocks of at most 65535 bytes
**     (the 16-bit LEN of RFC 1951): images just under, at and past one
**     block decode (tests/util.c's decoder, written apart);
**   - trace --direct reads rays in slices of 2^18: a file of 2^18 + 3
**     rays gets the brute-force answer for every ray, hits and occlusion;
**   - proxy resolutions are the powers of two 2..1024: 1024 is read,
**     2048, 1 and 3 refused;
**   - hitdiff's --t-rel is a largest difference, inclusive: identical
**     files agree at --t-rel 0;
**   - an instance's transform may have a condition number of at most 1024
**     (BRT_MAX_CONDITION), inclusive: diag(1, 1, 1024) and its mirror are
**     taken, diag(1, 1, 1025) refused (the norms are exact here: row sums
**     of a diagonal matrix and of its inverse, powers of two or not);
**   - pbrt-v4 Includes nest at most 64 files deep, the main file counted
**     (examples/lib/pbrt.c, MAX_DEPTH): 64 are read, the Include of a 65th is
**     refused at its line.
*/
#include "test.h"
#include "util.h"
#include "examples/lib/common.h"
#include "examples/lib/scenes.h"
#include "examples/lib/pbrt.h"

#include <math.h>
#include <stdio.h>
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

/* ---- instances in chunks ---- */

typedef struct instance_log {
    const ex_instanced_scene *scene;
    uint32_t next, wrong;
    brt_instance *all;
} instance_log;

static brt_result log_instances(void *user, const brt_instance *instances, uint32_t count, uint32_t first,
                                brt_error *err)
{
    instance_log *log = user;
    uint32_t i;
    (void)err;
    for (i = 0; i < count; i++) {
        brt_instance want;
        ex_instanced_instance(log->scene, first + i, &want);
        log->wrong += first + i != log->next + i || memcmp(&want, &instances[i], sizeof want) != 0;
        log->all[first + i < log->next + count ? first + i : 0] = instances[i];
    }
    log->next += count;
    return BRT_OK;
}

static int by_transform(const void *a, const void *b)
{
    return memcmp(((const brt_instance *)a)->xform, ((const brt_instance *)b)->xform,
                  sizeof ((const brt_instance *)a)->xform);
}

static void test_instances_past_one_chunk(void)
{
    ex_instanced_scene *s = NULL;
    brt_scene_source src;
    brt_error err;
    instance_log log;
    double scale = 1;
    uint32_t total = 0, i, same = 0;
    /* The smallest scale (in steps of 1) of more than two chunks and a part. */
    while (scale < 64) {
        uint64_t unique, instanced;
        ex_instanced_counts("landscape", scale, &unique, &instanced, &total);
        if (total > 2 * EX_INSTANCE_CHUNK + 1) break;
        scale += 1;
    }
    CHECK(total > 2 * EX_INSTANCE_CHUNK + 1, "no landscape of more than %d instances", 2 * EX_INSTANCE_CHUNK);
    CHECK(ex_instanced_open("landscape", scale, test_seed(), &s, &err) == BRT_OK, "%s", err.message);
    memset(&log, 0, sizeof log);
    log.scene = s;
    log.all = calloc(total, sizeof *log.all);
    CHECK(log.all, "out of memory");
    ex_instanced_source(s, &src);
    EXPECT(src.instances(src.user, log_instances, &log, &err) == BRT_OK, "%s", err.message);
    EXPECT(log.next == total && log.wrong == 0, "%u of %u instances streamed, %u not the one of their number",
           log.next, total, log.wrong);
    qsort(log.all, total, sizeof *log.all, by_transform);
    for (i = 1; i < total; i++) same += by_transform(&log.all[i - 1], &log.all[i]) == 0;
    EXPECT(same == 0, "%u instances placed as another one", same);
    free(log.all);
    ex_instanced_close(s);
}

/* ---- PNG blocks ---- */

static void test_png_blocks(void)
{
    /* raw bytes = height * (1 + 3 width): 65532, 65535, 65536, and three blocks */
    static const int sizes[][2] = {{1, 16383}, {28, 771}, {1, 16384}, {100, 700}};
    size_t k;
    for (k = 0; k < sizeof sizes / sizeof *sizes; k++) {
        int w = sizes[k][0], h = sizes[k][1], dw = 0, dh = 0;
        size_t n = (size_t)w * (size_t)h * 3, i, size = 0;
        unsigned char *rgb = malloc(n), *png = NULL, *back;
        CHECK(rgb, "out of memory");
        for (i = 0; i < n; i++) rgb[i] = (unsigned char)(i * 7 + i / 251);
        CHECK(ex_png_encode_rgb(w, h, rgb, &png, &size) == BRT_OK, "encode %dx%d", w, h);
        back = tu_png_decode(png, size, &dw, &dh);
        EXPECT(back && dw == w && dh == h && memcmp(back, rgb, n) == 0, "%dx%d (%d raw bytes) does not decode to itself",
               w, h, h * (1 + 3 * w));
        free(back);
        free(png);
        free(rgb);
    }
}

/* ---- trace --direct in slices ---- */

static void test_direct_slices(void)
{
    const size_t count = ((size_t)1 << 18) + 3;
    static const float v[3][3] = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
    brt_ray *rays = malloc(count * sizeof *rays);
    unsigned char *out = NULL, *occ = NULL;
    uint64_t st = test_seed() + 218;
    size_t i, size = 0, occ_size = 0, wrong = 0, wrong_occ = 0;
    FILE *f;
    CHECK(rays, "out of memory");
    for (i = 0; i < count; i++) {
        brt_ray *r = &rays[i];
        /* rays down onto the plane z = 0 over [-0.5, 1.5]^2: about a third hit */
        r->org[0] = tu_rnd(&st, -0.5f, 1.5f);
        r->org[1] = tu_rnd(&st, -0.5f, 1.5f);
        r->org[2] = 1;
        r->dir[0] = r->dir[1] = 0;
        r->dir[2] = -1;
        r->tnear = 0;
        r->tfar = INFINITY;
    }
    f = fopen(tu_scratch("tri.obj"), "w");
    CHECK(f, "cannot write tri.obj");
    fprintf(f, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
    fclose(f);
    EXPECT(tu_spill(tu_scratch("slices.rays"), rays, count * sizeof *rays), "cannot write the rays");
    EXPECT(tu_run("trace @/tri.obj @/slices.rays @/slices.hits --direct") == 0, "trace: %s", tu_last_stderr());
    EXPECT(tu_run("trace @/tri.obj @/slices.rays @/slices.occ --direct --occlusion") == 0, "trace: %s",
           tu_last_stderr());
    out = tu_slurp(tu_scratch("slices.hits"), &size);
    occ = tu_slurp(tu_scratch("slices.occ"), &occ_size);
    if (!out || size != count * 16 || !occ || occ_size != count) {
        EXPECT(0, "hit file of %zu bytes, occlusion file of %zu, for %zu rays", size, occ_size, count);
        goto done;
    }
    for (i = 0; i < count; i++) {
        brt_hit want, got;
        float t, u, w;
        brt_hit_clear(&want);
        if (brt_intersect_triangle(&rays[i], v[0], v[1], v[2], &t, &u, &w)) {
            want.t = t;
            want.prim = 0;
            want.u = u;
            want.v = w;
        }
        memcpy(&got.t, out + 16 * i, 4);         /* the 16-byte record: t, prim, u, v */
        memcpy(&got.prim, out + 16 * i + 4, 4);
        memcpy(&got.u, out + 16 * i + 8, 4);
        memcpy(&got.v, out + 16 * i + 12, 4);
        wrong += memcmp(&want.t, &got.t, 4) != 0 || want.prim != got.prim || memcmp(&want.u, &got.u, 4) != 0 ||
                 memcmp(&want.v, &got.v, 4) != 0;
        wrong_occ += occ[i] != (want.prim == 0);
    }
    EXPECT(wrong == 0 && wrong_occ == 0, "%zu hits and %zu occlusion bytes of %zu rays differ from brute force", wrong,
           wrong_occ, count);
done:
    free(out);
    free(occ);
    free(rays);
}

/* ---- proxy resolutions ---- */

static void test_resolution_bounds(void)
{
    static const struct { int res, ok; } cases[] = {{1024, 1}, {2048, 0}, {1, 0}, {3, 0}, {2, 1}};
    FILE *f = fopen(tu_scratch("res.obj"), "w");
    size_t i;
    CHECK(f, "cannot write res.obj");
    fprintf(f, "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n");
    fclose(f);
    for (i = 0; i < sizeof cases / sizeof *cases; i++) {
        int status = tu_run("voxelize @/res.obj --proxy-res %d --stats @/res.json", cases[i].res);
        double voxels = status == 0 ? tu_json_file_number(tu_scratch("res.json"), "voxels") : 0;
        if (cases[i].ok)
            EXPECT(status == 0 && voxels >= cases[i].res, "voxelize --proxy-res %d: status %d (%s), %g voxels", cases[i].res,
                   status, tu_last_stderr(), voxels);
        else
            EXPECT(status == 1 && strstr(tu_last_stderr(), "res"), "voxelize --proxy-res %d: status %d, '%s'", cases[i].res,
                   status, tu_last_stderr());
    }
    {   /* the batched mode too: one ray down onto the first triangle */
        brt_ray ray = {{0.25f, 0.25f, 1}, {0, 0, -1}, 0, INFINITY};
        unsigned char *hit;
        size_t size = 0;
        float t = 0;
        CHECK(tu_spill(tu_scratch("res.rays"), &ray, sizeof ray), "cannot write res.rays");
        EXPECT(tu_run("trace @/res.obj @/res.rays @/res.hits --batched --proxy-res 1024 --scene @/res.brs") == 0,
               "trace --batched --proxy-res 1024: %s", tu_last_stderr());
        hit = tu_slurp(tu_scratch("res.hits"), &size);
        if (hit && size == 16) memcpy(&t, hit, 4);
        EXPECT(t == 1.0f, "trace --batched --proxy-res 1024: t %g, want 1", t);
        free(hit);
    }
}

/* ---- hitdiff's tolerance ---- */

static void test_hitdiff_tolerance_inclusive(void)
{
    float hits[3][4];       /* 16-byte records: t, prim (bits), u, v */
    size_t i;
    for (i = 0; i < 3; i++) {
        uint32_t prim = (uint32_t)i;
        hits[i][0] = 1.5f + (float)i;
        memcpy(&hits[i][1], &prim, 4);
        hits[i][2] = hits[i][3] = 0.25f;
    }
    CHECK(tu_spill(tu_scratch("same.hits"), hits, sizeof hits), "cannot write");
    EXPECT(tu_run("hitdiff @/same.hits @/same.hits --t-rel 0 --max-disagree 0") == 0,
           "identical files at --t-rel 0: status not 0: %s%s", tu_last_stdout(), tu_last_stderr());
}

/* ---- the condition number's limit ---- */

static void test_condition_limit(void)
{
    static const struct { float x, z; int ok; } cases[] = {{1, 1024, 1}, {-1, 1024, 1}, {1, 1025, 0}, {1, 1024.001f, 0}};
    size_t i;
    for (i = 0; i < sizeof cases / sizeof *cases; i++) {
        brt_instance inst;
        brt_instance_frame frame;
        brt_error err;
        brt_result r;
        memset(&inst, 0, sizeof inst);
        inst.xform[0] = cases[i].x;
        inst.xform[5] = 1;
        inst.xform[10] = cases[i].z;
        r = brt_instance_frame_init(&inst, 7, &frame, &err);
        if (cases[i].ok)
            EXPECT(r == BRT_OK, "diag(%g, 1, %g): refused: %s", cases[i].x, cases[i].z, err.message);
        else
            EXPECT(r == BRT_EARG && strstr(err.message, "instance 7"), "diag(%g, 1, %g): %s", cases[i].x, cases[i].z,
                   r == BRT_OK ? "accepted" : err.message);
    }
}

/* A chain of pbrt files, the main one and depth - 1 Includes, the last
** holding one triangle; the result of opening it. */
static brt_result open_include_chain(int depth, brt_error *err)
{
    char name[64], text[128], main_path[600] = "";
    ex_pbrt *scene = NULL;
    brt_result r;
    int i;
    for (i = 0; i < depth; i++) {
        snprintf(name, sizeof name, "chain%d/f%d.pbrt", depth, i);
        if (i == depth - 1)
            snprintf(text, sizeof text, "Shape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0]\n");
        else snprintf(text, sizeof text, "%sInclude \"f%d.pbrt\"\n", i == 0 ? "WorldBegin\n" : "", i + 1);
        if (i == 0) snprintf(main_path, sizeof main_path, "%s", tu_put(name, text));   /* tu_put's buffers rotate */
        else tu_put(name, text);
    }
    r = ex_pbrt_open(main_path, &scene, err);
    if (r == BRT_OK) {
        uint64_t shapes = 0;
        ex_pbrt_counts(scene, &shapes, NULL, NULL);
        if (shapes != 1) r = brt_fail(err, BRT_EPARSE, "%llu shapes, expected 1", (unsigned long long)shapes);
        ex_pbrt_close(scene);
    }
    return r;
}

static void test_include_depth(void)
{
    brt_error err;
    brt_result r = open_include_chain(64, &err);
    EXPECT(r == BRT_OK, "64 files deep: %s", err.message);
    r = open_include_chain(65, &err);
    EXPECT(r == BRT_EPARSE && strstr(err.message, "chain65/f63.pbrt:1: Includes nested more than 64 deep"),
           "65 files deep: result %d, '%s'", r, r == BRT_OK ? "" : err.message);
}

void suite_thresholds(void)
{
    test_run("thresholds: a blob larger than one cache read (8 MiB) == direct", test_blob_past_one_read);
    test_run("thresholds: PLY headers of 16 elements and 64 properties, one past each", test_ply_header_limits);
    test_run("thresholds: instanced scenes stream past one chunk of 4096 instances", test_instances_past_one_chunk);
    test_run("thresholds: PNG pixels under, at and past one stored block (65535 bytes)", test_png_blocks);
    test_run("thresholds: trace --direct past its slice of 2^18 rays == brute force", test_direct_slices);
    test_run("thresholds: proxy resolution 1024 read, 2048, 1 and 3 refused", test_resolution_bounds);
    test_run("thresholds: hitdiff --t-rel is inclusive: identical files agree at 0", test_hitdiff_tolerance_inclusive);
    test_run("thresholds: an instance's condition number 1024 taken, 1025 refused", test_condition_limit);
    test_run("thresholds: pbrt Includes 64 files deep read, 65 refused", test_include_depth);
}
