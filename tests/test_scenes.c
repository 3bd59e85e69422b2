/*
** tests/test_scenes.c -- the built-in procedural scenes (examples/lib/scenes.c)
** and build/mkscene: determinism from the seed (hashes of the arrays),
** size proportional to the scale, well-formed meshes (finite coordinates,
** indices in range, every vertex used, no zero-area triangles), the
** crown's closedness checked with sorted directed edges (each edge once in
** each direction) and its outward orientation with the divergence theorem
** (signed volume > 0), default views whose central ray hits the scene
** (brute force over brt_intersect_triangle), and mkscene's files read back
** by brt_mesh_load to the same floats and indices.
**
** The streamed outputs (README, "Building scene files out of core") against the collector: the triangle
** stream's corners equal the indexed arrays' triangles in order, in the
** same chunks on every run; counts equal; a scene file built from the
** stream has the mesh's bounds bit for bit (render's camera comes from
** them); the stamp follows the recipe; and mkscene, which streams, stays
** far below the mesh's bytes in peak memory.
*/
#include "test.h"
#include "util.h"
#include "batchrt.h"
#include "../examples/lib/scenes.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <stdio.h>
#include <sys/stat.h>

#define SCENES 3

static const char *const scene_list[SCENES] = {"crown", "landscape", "island"};

/* Scale factors that give each scene about the crown's triangles: the
** landscape and the island are baked from their instances (about 6.5 M
** and 4 M triangles at scale 1), the crown about 100 thousand. */
static const double per_scale[SCENES] = {1, 1.0 / 64, 1.0 / 40};

static int generate(const char *name, double scale, uint64_t seed, brt_mesh *mesh)
{
    brt_error err;
    brt_result r = ex_scene_generate(name, scale, seed, mesh, &err);
    if (r != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s at scale %g: %s", name, scale, err.message);
        return 0;
    }
    return 1;
}

/* FNV-1a over both arrays: a change of any byte changes it (practically). */
static uint64_t mesh_hash(const brt_mesh *m)
{
    const unsigned char *parts[2];
    size_t sizes[2], i;
    uint64_t h = 14695981039346656037ull;
    int p;
    parts[0] = (const unsigned char *)m->positions;
    sizes[0] = 3 * sizeof(float) * (size_t)m->vertex_count;
    parts[1] = (const unsigned char *)m->indices;
    sizes[1] = 3 * sizeof(uint32_t) * (size_t)m->triangle_count;
    for (p = 0; p < 2; p++)
        for (i = 0; i < sizes[p]; i++) h = (h ^ parts[p][i]) * 1099511628211ull;
    return h;
}

static void test_same_seed_same_bytes(void)
{
    uint64_t seed = test_seed();
    int s;
    for (s = 0; s < SCENES; s++) {
        brt_mesh a, b, c;
        if (!generate(scene_list[s], 0.3 * per_scale[s], seed, &a)) return;
        if (!generate(scene_list[s], 0.3 * per_scale[s], seed, &b)) return;
        if (!generate(scene_list[s], 0.3 * per_scale[s], seed + 1, &c)) return;
        EXPECT(a.vertex_count == b.vertex_count && a.triangle_count == b.triangle_count
               && mesh_hash(&a) == mesh_hash(&b),
               "%s: seed %llu gave different meshes twice", scene_list[s], (unsigned long long)seed);
        EXPECT(mesh_hash(&a) != mesh_hash(&c), "%s: seeds %llu and %llu gave the same mesh",
               scene_list[s], (unsigned long long)seed, (unsigned long long)seed + 1);
        brt_mesh_free(&a);
        brt_mesh_free(&b);
        brt_mesh_free(&c);
    }
}

/* And the landscape and the island are their instanced scenes baked:
** as many triangles as those have instanced (ex_instanced_counts). */
static void test_size_follows_scale(void)
{
    int s;
    for (s = 0; s < SCENES; s++) {
        brt_mesh one, four;
        double ratio;
        uint64_t unique, instanced;
        uint32_t instances;
        if (!generate(scene_list[s], per_scale[s], test_seed(), &one)) return;
        if (!generate(scene_list[s], 4 * per_scale[s], test_seed(), &four)) return;
        ratio = (double)four.triangle_count / one.triangle_count;
        EXPECT(one.triangle_count >= 50000 && one.triangle_count <= 200000,
               "%s: %lu triangles at scale %g", scene_list[s], (unsigned long)one.triangle_count,
               per_scale[s]);
        EXPECT(ratio >= 4 / 1.5 && ratio <= 4 * 1.5, "%s: 4 times the scale has %.2f times the "
               "triangles", scene_list[s], ratio);
        ex_instanced_counts(scene_list[s], per_scale[s], &unique, &instanced, &instances);
        EXPECT(s == 0 || instanced == one.triangle_count, "%s: %lu triangles baked, %llu "
               "instanced", scene_list[s], (unsigned long)one.triangle_count,
               (unsigned long long)instanced);
        brt_mesh_free(&one);
        brt_mesh_free(&four);
    }
}

static int zero_area(const brt_mesh *m, uint32_t t)
{
    const float *a = m->positions + 3 * (size_t)m->indices[3 * (size_t)t];
    const float *b = m->positions + 3 * (size_t)m->indices[3 * (size_t)t + 1];
    const float *c = m->positions + 3 * (size_t)m->indices[3 * (size_t)t + 2];
    /* Edges of floats are exact in double; their cross product too up to
    ** rounding that cannot turn a nonzero component into zero. */
    double e[3], f[3];
    int k;
    for (k = 0; k < 3; k++) {
        e[k] = (double)b[k] - a[k];
        f[k] = (double)c[k] - a[k];
    }
    return e[1] * f[2] == e[2] * f[1] && e[2] * f[0] == e[0] * f[2] && e[0] * f[1] == e[1] * f[0];
}

/* Finite coordinates, indices in range, every vertex used, at most one
** zero-area triangle in 10000. */
static void check_well_formed(const char *name, const brt_mesh *m)
{
    unsigned char *used = calloc(m->vertex_count ? m->vertex_count : 1, 1);
    uint32_t i, degenerate = 0;
    CHECK(used != NULL, "out of memory");
    for (i = 0; i < 3 * m->vertex_count; i++)
        if (!isfinite(m->positions[i])) break;
    EXPECT(i == 3 * m->vertex_count, "%s: coordinate %lu is not finite", name, (unsigned long)i);
    for (i = 0; i < 3 * m->triangle_count; i++) {
        if (m->indices[i] >= m->vertex_count) break;
        used[m->indices[i]] = 1;
    }
    if (i < 3 * m->triangle_count) {
        test_fail_at(__FILE__, __LINE__, "%s: index %lu out of range", name, (unsigned long)i);
        free(used);
        return;
    }
    for (i = 0; i < m->vertex_count && used[i]; i++) {}
    EXPECT(i == m->vertex_count, "%s: vertex %lu is never used", name, (unsigned long)i);
    for (i = 0; i < m->triangle_count; i++) degenerate += zero_area(m, i);
    EXPECT(degenerate <= m->triangle_count / 10000, "%s: %lu zero-area triangles of %lu", name,
           (unsigned long)degenerate, (unsigned long)m->triangle_count);
    free(used);
}

/* Scale 20 (2 million triangles) makes the finest grids fine enough for
** float rounding to flatten thin triangles near poles and tips. */
static void test_well_formed(void)
{
    static const double scales[] = {0.01, 1, 20};
    int s, k;
    for (s = 0; s < SCENES; s++)
        for (k = 0; k < 3; k++) {
            brt_mesh m;
            if (!generate(scene_list[s], scales[k] * per_scale[s], test_seed() + (uint64_t)k, &m))
                return;
            check_well_formed(scene_list[s], &m);
            brt_mesh_free(&m);
        }
}

static int compare_u64(const void *a, const void *b)
{
    uint64_t x = *(const uint64_t *)a, y = *(const uint64_t *)b;
    return x < y ? -1 : x > y;
}

static uint32_t find_root(uint32_t *parent, uint32_t v)
{
    while (parent[v] != v) v = parent[v] = parent[parent[v]];
    return v;
}

static double signed_volume(const brt_mesh *m, uint32_t t)
{
    const float *a = m->positions + 3 * (size_t)m->indices[3 * (size_t)t];
    const float *b = m->positions + 3 * (size_t)m->indices[3 * (size_t)t + 1];
    const float *c = m->positions + 3 * (size_t)m->indices[3 * (size_t)t + 2];
    return ((double)a[0] * ((double)b[1] * c[2] - (double)b[2] * c[1])
          - (double)a[1] * ((double)b[0] * c[2] - (double)b[2] * c[0])
          + (double)a[2] * ((double)b[0] * c[1] - (double)b[1] * c[0])) / 6;
}

/* Divergence theorem: a closed part whose triangles face outwards encloses
** a positive signed volume.  Parts are the connected components of the
** index graph (union-find), so one inward part cannot hide behind others. */
static void check_parts_face_outwards(const brt_mesh *m)
{
    uint32_t *parent = malloc(m->vertex_count * sizeof *parent), i, parts = 0, inward = 0;
    double *volume = calloc(m->vertex_count, sizeof *volume);
    CHECK(parent && volume, "out of memory");
    for (i = 0; i < m->vertex_count; i++) parent[i] = i;
    for (i = 0; i < 3 * m->triangle_count; i++) {
        uint32_t a = find_root(parent, m->indices[i]);
        uint32_t b = find_root(parent, m->indices[i % 3 == 2 ? i - 2 : i + 1]);
        parent[a] = b;
    }
    for (i = 0; i < m->triangle_count; i++)
        volume[find_root(parent, m->indices[3 * i])] += signed_volume(m, i);
    for (i = 0; i < m->vertex_count; i++) {
        if (parent[i] != i) continue;
        parts++;
        inward += !(volume[i] > 0);
    }
    EXPECT(inward == 0, "%lu of %lu parts of the crown enclose no positive volume",
           (unsigned long)inward, (unsigned long)parts);
    EXPECT(parts > 100, "only %lu parts", (unsigned long)parts);
    free(parent);
    free(volume);
}

/* Closed and consistently oriented: each directed edge a->b occurs exactly
** once and so does b->a (so each edge has exactly two triangles, which
** traverse it in opposite directions). */
static void test_crown_closed_and_outward(void)
{
    brt_mesh m;
    uint64_t *edges;
    size_t n, i;
    if (!generate("crown", 1, test_seed(), &m)) return;
    n = 3 * (size_t)m.triangle_count;
    edges = malloc(n * sizeof *edges);
    CHECK(edges != NULL, "out of memory");
    for (i = 0; i < n; i++) {
        uint64_t a = m.indices[i], b = m.indices[i % 3 == 2 ? i - 2 : i + 1];
        edges[i] = a << 32 | b;
    }
    qsort(edges, n, sizeof *edges, compare_u64);
    for (i = 0; i < n && !test_failed(); i++) {
        uint64_t reverse = edges[i] << 32 | edges[i] >> 32;
        EXPECT(i + 1 == n || edges[i + 1] != edges[i], "edge %lu->%lu occurs twice",
               (unsigned long)(edges[i] >> 32), (unsigned long)(edges[i] & 0xFFFFFFFFu));
        EXPECT(bsearch(&reverse, edges, n, sizeof *edges, compare_u64) != NULL,
               "edge %lu->%lu has no opposite", (unsigned long)(edges[i] >> 32),
               (unsigned long)(edges[i] & 0xFFFFFFFFu));
    }
    check_parts_face_outwards(&m);
    free(edges);
    brt_mesh_free(&m);
}

static void test_names_and_errors(void)
{
    const char *const *names = ex_scene_names();
    brt_mesh m;
    brt_error err;
    static const double bad_scales[] = {0, -1, EX_SCENE_MAX_SCALE * 2};
    int s;
    for (s = 0; s < SCENES; s++) {
        CHECK(names[s] && strcmp(names[s], scene_list[s]) == 0, "name %d", s);
        EXPECT(ex_scene_is_builtin(names[s]), "%s not built in", names[s]);
    }
    EXPECT(names[SCENES] == NULL, "names not NULL-terminated after %d", SCENES);
    EXPECT(!ex_scene_is_builtin("crowns") && !ex_scene_is_builtin("") && !ex_scene_is_builtin(NULL),
           "unknown names reported as built in");
    EXPECT(ex_scene_generate("teapot", 1, 1, &m, &err) == BRT_EARG && m.positions == NULL
           && strstr(err.message, "teapot"), "unknown scene: %s", err.message);
    for (s = 0; s < 3; s++)
        EXPECT(ex_scene_generate("crown", bad_scales[s], 1, &m, &err) == BRT_EARG
               && m.positions == NULL, "scale %g accepted", bad_scales[s]);
    EXPECT(ex_scene_generate("crown", nan(""), 1, &m, &err) == BRT_EARG, "NaN scale accepted");
}

/* Does the ray hit any triangle of the mesh?  (Brute force.) */
static int mesh_hit(const brt_mesh *m, const brt_ray *ray)
{
    uint32_t i;
    float t, u, v;
    for (i = 0; i < m->triangle_count; i++)
        if (brt_intersect_triangle(ray, m->positions + 3 * (size_t)m->indices[3 * i],
                                   m->positions + 3 * (size_t)m->indices[3 * i + 1],
                                   m->positions + 3 * (size_t)m->indices[3 * i + 2], &t, &u, &v))
            return 1;
    return 0;
}

/* The ray from the default eye through the target hits the scene (brute
** force), and the eye is in the open: nothing above it (so it is not
** inside an object, under the terrain or under a tree), and either
** outside the scene's box or above some geometry (the landscape's low
** view looks from inside the box, over the terrain). */
static void test_default_view_sees_the_scene(void)
{
    static const float up[3] = {0, 1, 0}, down[3] = {0, -1, 0};
    int s, k;
    for (s = 0; s < SCENES; s++) {
        brt_mesh m;
        brt_ray ray, vertical;
        float lo[3], hi[3], target[3], fov;
        int outside = 0, covered, grounded;
        if (!generate(scene_list[s], 0.2 * per_scale[s], test_seed(), &m)) return;
        brt_mesh_bounds(&m, lo, hi);
        ex_scene_camera(scene_list[s], lo, hi, ray.org, target, &fov);
        for (k = 0; k < 3; k++) {
            ray.dir[k] = target[k] - ray.org[k];
            outside |= ray.org[k] < lo[k] || ray.org[k] > hi[k];
        }
        ray.tnear = 0;
        ray.tfar = INFINITY;
        vertical = ray;
        memcpy(vertical.dir, up, sizeof up);
        covered = mesh_hit(&m, &vertical);
        memcpy(vertical.dir, down, sizeof down);
        grounded = mesh_hit(&m, &vertical);
        EXPECT(mesh_hit(&m, &ray), "%s: the central ray of the default view misses", scene_list[s]);
        EXPECT(!covered, "%s: the default eye is under or inside geometry", scene_list[s]);
        EXPECT(outside || grounded, "%s: the default eye is in the box but over no ground",
               scene_list[s]);
        EXPECT(fov > 10 && fov < 120, "%s: field of view %g", scene_list[s], fov);
        brt_mesh_free(&m);
    }
}

/* Runs build/mkscene with the arguments; returns its exit status. */
static int run_mkscene(const char *args, const char *stderr_path)
{
    char cmd[2048];
    const char *build = getenv("BRT_BUILD");
    snprintf(cmd, sizeof cmd, "'%s/mkscene' %s > /dev/null 2> '%s'", build ? build : "build",
             args, stderr_path);
    return system(cmd);
}

static void check_file_equals_scene(const char *path, const char *name, double scale,
                                    uint64_t seed)
{
    brt_mesh loaded, made;
    brt_error err;
    CHECK(brt_mesh_load(path, &loaded, &err) == BRT_OK, "%s: %s", path, err.message);
    if (generate(name, scale, seed, &made)) {
        EXPECT(loaded.vertex_count == made.vertex_count && loaded.triangle_count == made.triangle_count
               && memcmp(loaded.positions, made.positions, 12 * (size_t)made.vertex_count) == 0
               && memcmp(loaded.indices, made.indices, 12 * (size_t)made.triangle_count) == 0,
               "%s does not read back as %s (scale %g, seed %llu)", path, name, scale,
               (unsigned long long)seed);
        brt_mesh_free(&made);
    }
    brt_mesh_free(&loaded);
}

static void test_mkscene_files_read_back(void)
{
    char args[1024], out[512], err_path[512], message[64] = {0};
    uint64_t seed = test_seed() % 1000000;
    struct stat st;
    FILE *f;
    snprintf(err_path, sizeof err_path, "%s/mkscene.err", test_tmpdir());
    snprintf(out, sizeof out, "%s/crown.ply", test_tmpdir());
    snprintf(args, sizeof args, "crown '%s' --scale 0.2 --seed %llu", out, (unsigned long long)seed);
    CHECK(run_mkscene(args, err_path) == 0, "mkscene %s failed", args);
    check_file_equals_scene(out, "crown", 0.2, seed);

    snprintf(out, sizeof out, "%s/island.obj", test_tmpdir());
    snprintf(args, sizeof args, "island '%s' --scale 0.002 --seed %llu", out, (unsigned long long)seed);
    CHECK(run_mkscene(args, err_path) == 0, "mkscene %s failed", args);
    check_file_equals_scene(out, "island", 0.002, seed);

    snprintf(out, sizeof out, "%s/none.ply", test_tmpdir());
    snprintf(args, sizeof args, "teapot '%s'", out);
    EXPECT(run_mkscene(args, err_path) != 0, "mkscene accepted an unknown scene");
    EXPECT(stat(out, &st) != 0, "mkscene left %s behind after an error", out);
    f = fopen(err_path, "r");
    CHECK(f != NULL, "no stderr file");
    EXPECT(fgets(message, sizeof message, f) && strncmp(message, "mkscene: ", 9) == 0,
           "stderr was '%s'", message);
    fclose(f);
}

/* ---- the streamed outputs ---- */

/* Collects a triangle stream and checks its chunk numbering. */
typedef struct corner_log {
    float *corners;
    uint64_t count, cap;
    uint32_t chunks;
    int misnumbered;             /* a chunk's first was not the count so far */
    uint64_t chunk_hash;         /* of the chunk sizes, in order */
} corner_log;

static brt_result log_corners(void *user, const float *corners, uint32_t count, uint32_t first,
                              brt_error *err)
{
    corner_log *log = user;
    (void)err;
    if (first != log->count) log->misnumbered = 1;
    if (log->count + count > log->cap) {
        uint64_t cap = 2 * (log->count + count);
        float *bigger = realloc(log->corners, 36 * (size_t)cap);
        if (!bigger) return BRT_ENOMEM;
        log->corners = bigger;
        log->cap = cap;
    }
    memcpy(log->corners + 9 * (size_t)log->count, corners, 36 * (size_t)count);
    log->count += count;
    log->chunks++;
    log->chunk_hash = (log->chunk_hash ^ count) * 1099511628211ull;
    return BRT_OK;
}

/* Triangle i of the stream is the collector's triangle i, corner by
** corner, bit for bit. */
static int stream_matches_mesh(const corner_log *log, const brt_mesh *m)
{
    uint64_t i;
    int c;
    if (log->count != m->triangle_count || log->misnumbered) return 0;
    for (i = 0; i < log->count; i++)
        for (c = 0; c < 3; c++)
            if (memcmp(log->corners + 9 * i + 3 * c,
                       m->positions + 3 * (size_t)m->indices[3 * i + c], 12) != 0)
                return 0;
    return 1;
}

/* Scale 2 gives the crown's band a grid of 60 thousand triangles: several
** batches, so the band-by-band emission and the batch boundaries inside a
** surface are exercised; the baked scenes hand on an instance a chunk. */
static void test_stream_equals_collector(void)
{
    static const double scales[] = {0.05, 2};
    int s, k;
    for (s = 0; s < SCENES; s++)
        for (k = 0; k < 2; k++) {
            ex_scene_recipe recipe;
            corner_log first, again;
            brt_mesh m;
            brt_error err;
            uint64_t vertices, triangles;
            recipe.name = scene_list[s];
            recipe.scale = scales[k] * per_scale[s];
            recipe.seed = test_seed();
            memset(&first, 0, sizeof first);
            memset(&again, 0, sizeof again);
            if (!generate(recipe.name, recipe.scale, recipe.seed, &m)) return;
            EXPECT(ex_scene_stream(&recipe, log_corners, &first, &err) == BRT_OK
                   && ex_scene_stream(&recipe, log_corners, &again, &err) == BRT_OK,
                   "%s: stream failed: %s", recipe.name, err.message);
            EXPECT(stream_matches_mesh(&first, &m), "%s at scale %g: the stream's %llu triangles "
                   "are not the collector's %lu", recipe.name, recipe.scale,
                   (unsigned long long)first.count, (unsigned long)m.triangle_count);
            EXPECT(first.chunks == again.chunks && first.chunk_hash == again.chunk_hash
                   && first.chunks >= (k == 0 ? 1u : 3u),
                   "%s: %u chunks, then %u on the second run", recipe.name, first.chunks,
                   again.chunks);
            EXPECT(ex_scene_count(&recipe, &vertices, &triangles, &err) == BRT_OK
                   && vertices == m.vertex_count && triangles == m.triangle_count,
                   "%s: counted %llu vertices and %llu triangles, made %lu and %lu", recipe.name,
                   (unsigned long long)vertices, (unsigned long long)triangles,
                   (unsigned long)m.vertex_count, (unsigned long)m.triangle_count);
            free(first.corners);
            free(again.corners);
            brt_mesh_free(&m);
        }
}

/* A consumer that fails stops the scene at once, with its result. */
static brt_result refuse_third_chunk(void *user, const float *corners, uint32_t count,
                                     uint32_t first, brt_error *err)
{
    int *calls = user;
    (void)corners;
    (void)count;
    (void)first;
    return ++*calls == 3 ? brt_fail(err, BRT_EINTR, "stop") : BRT_OK;
}

static void test_stream_stops_on_consumer_error(void)
{
    ex_scene_recipe recipe = {"landscape", 2.0 / 64, 1};
    brt_error err;
    int calls = 0;
    brt_result r = ex_scene_stream(&recipe, refuse_third_chunk, &calls, &err);
    EXPECT(r == BRT_EINTR && calls == 3 && strcmp(err.message, "stop") == 0,
           "result %d after %d calls: %s", (int)r, calls, err.message);
    recipe.name = "teapot";
    EXPECT(ex_scene_stream(&recipe, refuse_third_chunk, &calls, &err) == BRT_EARG
           && strstr(err.message, "teapot"), "unknown scene: %s", err.message);
}

/* The camera of a batched render comes from brt_scene_bounds, --direct's
** from brt_mesh_bounds: the union of the batching points' exact boxes is
** the minimum and maximum over the same floats, so they agree bit for bit
** (also in the sign of a zero), and so do the images. */
static void test_scene_file_has_mesh_bounds(void)
{
    int s;
    for (s = 0; s < SCENES; s++) {
        ex_scene_recipe recipe;
        brt_triangle_source source;
        brt_scene_options opt;
        brt_scene *scene;
        brt_mesh m;
        brt_error err;
        float mesh_lo[3], mesh_hi[3], lo[3], hi[3];
        char path[512];
        recipe.name = scene_list[s];
        recipe.scale = 0.05 * per_scale[s];
        recipe.seed = test_seed();
        snprintf(path, sizeof path, "%s/%s-bounds.brs", test_tmpdir(), recipe.name);
        memset(&opt, 0, sizeof opt);
        opt.point_tris = 700;
        opt.proxy_res = 8;
        ex_scene_source(&recipe, &source);
        CHECK(brt_scene_build_stream(&source, &opt, ex_scene_stamp(&recipe), path, &err) == BRT_OK
              && brt_scene_open(path, &scene, &err) == BRT_OK, "%s: %s", path, err.message);
        if (!generate(recipe.name, recipe.scale, recipe.seed, &m)) return;
        brt_mesh_bounds(&m, mesh_lo, mesh_hi);
        brt_scene_bounds(scene, lo, hi);
        EXPECT(memcmp(lo, mesh_lo, sizeof lo) == 0 && memcmp(hi, mesh_hi, sizeof hi) == 0,
               "%s: scene bounds %g %g %g .. %g %g %g, mesh bounds %g %g %g .. %g %g %g",
               recipe.name, lo[0], lo[1], lo[2], hi[0], hi[1], hi[2], mesh_lo[0], mesh_lo[1],
               mesh_lo[2], mesh_hi[0], mesh_hi[1], mesh_hi[2]);
        EXPECT(brt_scene_triangle_count(scene) == m.triangle_count
               && brt_scene_matches(scene, ex_scene_stamp(&recipe), &opt),
               "%s: %lu triangles in the scene file, %lu made", recipe.name,
               (unsigned long)brt_scene_triangle_count(scene), (unsigned long)m.triangle_count);
        brt_scene_close(scene);
        brt_mesh_free(&m);
        remove(path);
    }
}

/* The stamp is the recipe's: equal recipes, equal stamps; any field
** changed, another stamp. */
static void test_stamp_follows_recipe(void)
{
    ex_scene_recipe a = {"landscape", 3, 7}, b = a;
    uint64_t stamp = ex_scene_stamp(&a);
    EXPECT(ex_scene_stamp(&b) == stamp, "equal recipes, different stamps");
    b.name = "island";
    EXPECT(ex_scene_stamp(&b) != stamp, "the name does not change the stamp");
    b = a;
    b.scale = 3.0000001;
    EXPECT(ex_scene_stamp(&b) != stamp, "the scale does not change the stamp");
    b = a;
    b.seed = 8;
    EXPECT(ex_scene_stamp(&b) != stamp, "the seed does not change the stamp");
}

/* mkscene streams: the landscape at scale 10/64 (a million triangles,
** 40 MB as an indexed mesh) peaks under a fifth of the mesh's bytes;
** holding the mesh would take all of them. */
static void test_mkscene_holds_no_mesh(void)
{
    char cmd[2048], out[512], line[256] = {0}, *p;
    const char *build = getenv("BRT_BUILD");
    ex_scene_recipe recipe = {"landscape", 10.0 / 64, 1};
    uint64_t vertices, triangles;
    double peak_mib = -1, mesh_mib;
    brt_error err;
    FILE *f;
    CHECK(ex_scene_count(&recipe, &vertices, &triangles, &err) == BRT_OK, "%s", err.message);
    mesh_mib = 12.0 * (double)(vertices + triangles) / 1048576.0;
    snprintf(out, sizeof out, "%s/big.ply", test_tmpdir());
    snprintf(cmd, sizeof cmd, "'%s/mkscene' landscape '%s' --scale %.17g", build ? build : "build",
             out, recipe.scale);
    f = popen(cmd, "r");
    CHECK(f != NULL, "cannot run %s", cmd);
    CHECK(fgets(line, sizeof line, f) != NULL, "no output from %s", cmd);
    while (fgetc(f) != EOF) {}
    CHECK(pclose(f) == 0, "%s failed", cmd);
    if ((p = strstr(line, "peak RSS ")) != NULL) peak_mib = strtod(p + 9, NULL);
    if (tu_rss_is_meaningful())
        EXPECT(peak_mib > 0 && peak_mib < mesh_mib / 5, "mkscene at scale 10/64: peak RSS %.1f MiB, "
               "the mesh holds %.1f MiB ('%s')", peak_mib, mesh_mib, line);
    check_file_equals_scene(out, "landscape", recipe.scale, 1);
    remove(out);
}

void suite_scenes(void)
{
    test_run("scenes_same_seed_same_bytes", test_same_seed_same_bytes);
    test_run("scenes_size_follows_scale", test_size_follows_scale);
    test_run("scenes_well_formed", test_well_formed);
    test_run("scenes_crown_closed_and_outward", test_crown_closed_and_outward);
    test_run("scenes_names_and_errors", test_names_and_errors);
    test_run("scenes_default_view_sees_the_scene", test_default_view_sees_the_scene);
    test_run("scenes_mkscene_files_read_back", test_mkscene_files_read_back);
    test_run("scenes_stream_equals_collector", test_stream_equals_collector);
    test_run("scenes_stream_stops_on_consumer_error", test_stream_stops_on_consumer_error);
    test_run("scenes_scene_file_has_mesh_bounds", test_scene_file_has_mesh_bounds);
    test_run("scenes_stamp_follows_recipe", test_stamp_follows_recipe);
    test_run("scenes: mkscene holds no mesh (peak RSS at a million triangles), same file", test_mkscene_holds_no_mesh);
}
