/*
** tests/test_build.c -- triangle streams and the out-of-core scene build.
**
** The stream against brt_mesh_load (the same triangles, numbers and
** messages); scenes made by the streamed build against the direct mode,
** byte for byte, with the partition checker on every one: shared meshes,
** adversarial triangle sets and orders, buckets split once and again and
** larger than a spill chunk.  Then what the build must never do: leave a
** file behind after a write error or an interrupt, depend on its chunk
** size, or hold memory that grows with the triangle count (peak RSS of a
** child process, reset through /proc/self/clear_refs, with small buckets).
** Issue 32: forged blob extents with repaired checksums (2^64-1, past the
** end, off a page); the spill's own invariants (buckets spatial and full,
** chunks numbered in order).  (Temporary files of killed builds:
** tests/test_reclaim.c.)
*/
#define _DEFAULT_SOURCE   /* setitimer */
#include "test.h"
#include "util.h"
#include "fuzz/targets.h"

#include <dirent.h>
#include <math.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/time.h>
#include <sys/wait.h>
#include <unistd.h>

/* ---- helpers ------------------------------------------------------------- */

/* The build's knobs in one call: the options it returns (a zeroed struct
** is the default) and, for every build that follows, the bucket and the
** chunk (testing.h: brt_test_build_sizes; 0 is the default). */
static brt_scene_options build_options(uint32_t point_tris, uint32_t res, uint32_t bucket,
                                       uint32_t chunk)
{
    brt_scene_options opt;
    memset(&opt, 0, sizeof opt);
    opt.point_tris = point_tris;
    opt.proxy_res = res;
    brt_test_build_sizes(chunk, bucket);
    return opt;
}

/* A fresh empty directory in the scratch directory. */
static const char *fresh_dir(const char *name)
{
    static char path[512];
    snprintf(path, sizeof path, "%s/%s", test_tmpdir(), name);
    mkdir(path, 0700);
    return path;
}

/* Entries of a directory other than . and .., the first one's name in first. */
static int dir_entries(const char *dir, char first[256])
{
    DIR *d = opendir(dir);
    struct dirent *e;
    int n = 0;
    first[0] = 0;
    if (!d) return -1;
    while ((e = readdir(d)) != NULL) {
        if (strcmp(e->d_name, ".") == 0 || strcmp(e->d_name, "..") == 0) continue;
        if (n++ == 0) snprintf(first, 256, "%s", e->d_name);
    }
    closedir(d);
    return n;
}

/* Sampled rays of all four kinds: the batched scene's hits against one
** BVH over the whole mesh, byte for byte. */
static int hits_match(const tu_scene *s, brt_scene *scene, size_t per_kind, const char *what)
{
    size_t count = per_kind * TU_RAY_KINDS, i;
    brt_ray *rays = malloc(count * sizeof *rays);
    brt_hit *direct = malloc(count * sizeof *direct), *batched = malloc(count * sizeof *batched);
    brt_trace_options topt;
    brt_bvh *bvh = NULL;
    brt_error err;
    float lo[3], hi[3];
    uint64_t st = test_seed();
    int kind, ok = 1;
    tu_scene_bounds(s, lo, hi);
    for (kind = 0; kind < TU_RAY_KINDS; kind++)
        for (i = 0; i < per_kind; i++) tu_make_ray(s, lo, hi, kind, &st, &rays[(size_t)kind * per_kind + i]);
    if (brt_bvh_build(s->pos, s->idx, s->tcount, NULL, &bvh) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s: direct BVH build failed", what);
        ok = 0;
    }
    for (i = 0; ok && i < count; i++) {
        brt_hit_clear(&direct[i]);
        brt_bvh_intersect(bvh, &rays[i], &direct[i]);
    }
    memset(&topt, 0, sizeof topt);
    topt.memory_limit = 1;   /* one batching point at a time: every load through the cache */
    if (ok && brt_scene_trace(scene, &topt, rays, count, batched, NULL, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s: trace: %s", what, err.message);
        ok = 0;
    }
    for (i = 0; ok && i < count; i++)
        if (memcmp(&direct[i], &batched[i], sizeof *batched) != 0) {
            test_fail_at(__FILE__, __LINE__, "%s: ray %zu: batched t=%a prim=%u, direct t=%a prim=%u",
                         what, i, batched[i].t, (unsigned)batched[i].prim, direct[i].t,
                         (unsigned)direct[i].prim);
            ok = 0;
        }
    brt_bvh_free(bvh);
    free(rays);
    free(direct);
    free(batched);
    return ok;
}

/* Builds with opt from source, opens, checks the partition and the hits. */
static void build_and_compare(const tu_scene *s, const brt_triangle_source *source,
                              const brt_scene_options *opt, size_t per_kind, const char *what)
{
    const char *path = tu_scratch("build.brs");
    brt_scene *scene = NULL;
    brt_error err;
    if (brt_scene_build_stream(source, opt, 1, path, &err) != BRT_OK ||
        brt_scene_open(path, &scene, &err) != BRT_OK) {
        test_fail_at(__FILE__, __LINE__, "%s: %s", what, err.message);
        return;
    }
    if (brt_scene_triangle_count(scene) != s->tcount)
        test_fail_at(__FILE__, __LINE__, "%s: %u triangles in the scene, %u in the mesh", what,
                     brt_scene_triangle_count(scene), s->tcount);
    else if (brt_scene_check_partition(scene, opt->point_tris, &err) != BRT_OK)
        test_fail_at(__FILE__, __LINE__, "%s: %s", what, err.message);
    else
        hits_match(s, scene, per_kind, what);
    brt_scene_close(scene);
}

/* The same over a mesh in memory, with a bucket of a few batching points
** and a chunk smaller than a bucket, so every mesh of more than a bucket
** is split, scattered through several buffer flushes, and built. */
static void compare_memory(const tu_scene *s, uint32_t point_tris, const char *what)
{
    brt_mesh mesh = tu_mesh_view(s);
    brt_triangle_source source;
    brt_scene_options opt = build_options(point_tris, 16, 3 * point_tris, point_tris / 2 + 1);
    brt_mesh_memory_source(&mesh, &source);
    build_and_compare(s, &source, &opt, 300, what);
}

/* ---- the stream against brt_mesh_load ------------------------------------ */

typedef struct collected {
    float *corners;
    uint32_t count, chunks;
    int misnumbered;
} collected;

static brt_result collect(void *user, const float *corners, uint32_t count, uint32_t first,
                          brt_error *err)
{
    collected *c = user;
    float *more = realloc(c->corners, 9 * ((size_t)c->count + count) * sizeof *more);
    (void)err;
    if (!more) return BRT_ENOMEM;
    c->corners = more;
    if (first != c->count || count == 0) c->misnumbered = 1;
    memcpy(c->corners + 9 * (size_t)c->count, corners, 9 * (size_t)count * sizeof *corners);
    c->count += count;
    c->chunks++;
    return BRT_OK;
}

/* The stream of path gives brt_mesh_load's triangles in order, or its error. */
static void expect_stream_equals_load(const char *path, uint32_t min_chunks)
{
    brt_error load_err, stream_err;
    brt_mesh mesh;
    collected c;
    brt_result lr = brt_mesh_load(path, &mesh, &load_err);
    brt_result sr;
    uint32_t t;
    int k;
    memset(&c, 0, sizeof c);
    sr = brt_mesh_stream(path, collect, &c, &stream_err);
    if (lr != BRT_OK) {
        EXPECT(sr == lr && strcmp(load_err.message, stream_err.message) == 0,
               "%s: load says '%s', stream says '%s'", path, load_err.message,
               sr == BRT_OK ? "ok" : stream_err.message);
        free(c.corners);
        return;
    }
    EXPECT(sr == BRT_OK, "%s: %s", path, stream_err.message);
    EXPECT(!c.misnumbered, "%s: a chunk's first is not the count so far", path);
    EXPECT(c.chunks >= min_chunks, "%s: %u chunks, expected at least %u", path, c.chunks, min_chunks);
    EXPECT(c.count == mesh.triangle_count, "%s: %u triangles streamed, %u loaded", path, c.count,
           mesh.triangle_count);
    for (t = 0; t < c.count && t < mesh.triangle_count && !test_failed(); t++)
        for (k = 0; k < 9; k++)
            EXPECT(c.corners[9 * (size_t)t + k] ==
                       mesh.positions[3 * (size_t)mesh.indices[3 * (size_t)t + k / 3] + k % 3],
                   "%s: triangle %u corner value %d differs", path, t, k);
    brt_mesh_free(&mesh);
    free(c.corners);
}

/* An OBJ of n triangles (quads split in two), with a bad index after them
** when bad is set. */
static const char *write_big_obj(const char *name, uint32_t quads, int bad)
{
    const char *path = tu_scratch(name);
    FILE *f = fopen(path, "w");
    uint32_t i;
    if (!f) return NULL;
    for (i = 0; i < quads; i++) {
        fprintf(f, "v %u 0 0\nv %u 1 0\nv %u 1 1\nv %u 0 1\n", i, i, i, i);
        fprintf(f, "f %u %u %u %u\n", 4 * i + 1, 4 * i + 2, 4 * i + 3, 4 * i + 4);
    }
    if (bad) fprintf(f, "f 1 2 %u\n", 4 * quads + 7);
    return fclose(f) == 0 ? path : NULL;
}

static void test_stream_equals_load(void)
{
    /* Faces before vertices (legal PLY): the stream collects that tail. */
    static const char faces_first[] =
        "ply\nformat ascii 1.0\nelement face 3\nproperty list uchar int vertex_indices\n"
        "element vertex 5\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        "3 0 1 2\n4 1 2 3 4\n3 4 3 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n";
    static const char vertices_first[] =
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n3 3 2 9\n";
    const char *tiny = test_shared_mesh("bunny_tiny.obj");
    const char *big = write_big_obj("big.obj", 40000, 0), *bad = write_big_obj("bad.obj", 40000, 1);
    CHECK(big && bad, "cannot write the OBJ files");
    CHECK(tu_spill(tu_scratch("faces_first.ply"), faces_first, sizeof faces_first - 1) &&
          tu_spill(tu_scratch("bad_index.ply"), vertices_first, sizeof vertices_first - 1),
          "cannot write the PLY files");
    expect_stream_equals_load(big, 2);                 /* 80000 triangles: two chunks */
    expect_stream_equals_load(bad, 0);                 /* the error after a whole chunk */
    expect_stream_equals_load(tu_scratch("faces_first.ply"), 1);
    expect_stream_equals_load(tu_scratch("bad_index.ply"), 0);
    expect_stream_equals_load(tu_scratch("missing.obj"), 0);
    if (tiny) expect_stream_equals_load(tiny, 1);
    else test_skip("../shared/data/meshes/bunny_tiny.obj not present");
}

/* ---- batched == direct on streamed builds -------------------------------- */

/* Every shared mesh from its file (streamed, never loaded by the build),
** in about 20 batching points and buckets of 4: split, then built. */
static void test_shared_meshes(void)
{
    static const char *const names[] = {"bunny_tiny.obj", "bunny.obj.gz", "dragon.obj.gz",
                                        "bmw_m6.obj.gz", "fg_oahu.obj.gz", "crown.obj.gz"};
    size_t i;
    for (i = 0; i < sizeof names / sizeof names[0] && !test_failed(); i++) {
        const char *path = test_shared_mesh(names[i]);
        brt_triangle_source source;
        brt_scene_options opt;
        brt_mesh mesh;
        brt_error err;
        tu_scene s;
        if (!path) {
            test_skip("../shared/data/meshes/%s not present", names[i]);
            continue;
        }
        CHECK(brt_mesh_load(path, &mesh, &err) == BRT_OK, "%s", err.message);
        memset(&s, 0, sizeof s);
        s.pos = mesh.positions;
        s.idx = mesh.indices;
        s.vcount = mesh.vertex_count;
        s.tcount = mesh.triangle_count;
        opt = build_options(mesh.triangle_count / 20 + 1, 32, 4 * (mesh.triangle_count / 20 + 1), 0);
        brt_mesh_file_source(path, &source);
        build_and_compare(&s, &source, &opt, 250, names[i]);
        brt_mesh_free(&mesh);
    }
}

/* Adversarial sets: scaled and offset soups, tiny and flat triangles,
** degenerate ones, and a dense cluster inside a wide scene (its cell is a
** bucket of its own, split again in its own bounds). */
static void test_adversarial_sets(void)
{
    uint64_t st = test_seed() + 14;
    int which;
    for (which = 0; which < 5 && !test_failed(); which++) {
        tu_scene s;
        uint32_t i;
        memset(&s, 0, sizeof s);
        if (which == 0) tu_random_soup(&s, &st, 3000, 0.02f);
        if (which == 1) {
            tu_random_soup(&s, &st, 3000, 0.02f);
            tu_scene_transform(&s, 1e5f, 3e9f);
        }
        if (which == 2) {
            tu_random_soup(&s, &st, 3000, 0.3f);
            tu_scene_transform(&s, 1e-3f, 0.0f);
        }
        if (which == 3)   /* degenerate: points and needles, some repeated */
            for (i = 0; i < 3000; i++) {
                float x = tu_rnd(&st, 0, 1), y = tu_rnd(&st, 0, 1), z = tu_rnd(&st, 0, 1);
                float dx = i % 3 == 0 ? 0.0f : 0.01f;
                uint32_t a = tu_add_vertex(&s, x, y, z), b = tu_add_vertex(&s, x + dx, y, z);
                tu_add_triangle(&s, a, b, i % 5 == 0 ? a : tu_add_vertex(&s, x + 2 * dx, y, z));
            }
        if (which == 4) {
            tu_random_soup(&s, &st, 2500, 0.0003f);
            tu_scene_transform(&s, 0.001f, 0.5f);
            tu_random_soup(&s, &st, 500, 0.01f);
            tu_scene_transform(&s, 1e4f, 0.0f);
        }
        {
            char what[32];
            snprintf(what, sizeof what, "adversarial set %d", which);
            compare_memory(&s, 100, what);
        }
        tu_scene_free(&s);
    }
}

/* Triangles on one plane (z = 0, a grid of 60 x 50 quads), arriving
** sorted by x, in reverse, interleaved from both ends, and all of one
** position (one cell: cut in record order). */
static void test_adversarial_order(void)
{
    int order;
    for (order = 0; order < 4 && !test_failed(); order++) {
        static const char *const names[] = {"plane sorted", "plane reversed", "plane interleaved",
                                            "one triangle 3000 times"};
        tu_scene s;
        uint32_t k, n = 3000;
        memset(&s, 0, sizeof s);
        for (k = 0; k < n; k++) {
            uint32_t q = order == 0 ? k : order == 1 ? n - 1 - k
                       : (k % 2 ? n - 1 - k / 2 : k / 2);
            float x = order == 3 ? 0.0f : (float)(q / 2 / 50), y = order == 3 ? 0.0f : (float)(q / 2 % 50);
            uint32_t a = tu_add_vertex(&s, x, y, 0), b = tu_add_vertex(&s, x + 1, y, 0),
                     c = tu_add_vertex(&s, q % 2 ? x + 1 : x, y + 1, 0);
            tu_add_triangle(&s, a, b, c);
        }
        compare_memory(&s, 64, names[order]);
        tu_scene_free(&s);
    }
}

/* A bucket of 900 triangles read and written through spill chunks of 7:
** the scene equals the one built with the default chunk, byte for byte,
** and matches the direct mode. */
static void test_bucket_larger_than_chunk(void)
{
    uint64_t st = test_seed() + 15;
    tu_scene s;
    brt_mesh mesh;
    brt_triangle_source source;
    brt_scene_options opt;
    brt_error err;
    unsigned char *a, *b;
    size_t na = 0, nb = 0;
    memset(&s, 0, sizeof s);
    tu_random_soup(&s, &st, 5000, 0.02f);
    mesh = tu_mesh_view(&s);
    brt_mesh_memory_source(&mesh, &source);
    opt = build_options(100, 8, 900, 7);
    CHECK(brt_scene_build_stream(&source, &opt, 1, tu_scratch("chunk7.brs"), &err) == BRT_OK, "%s", err.message);
    opt = build_options(100, 8, 900, 0);
    CHECK(brt_scene_build_stream(&source, &opt, 1, tu_scratch("chunkd.brs"), &err) == BRT_OK, "%s", err.message);
    a = tu_slurp(tu_scratch("chunk7.brs"), &na);
    b = tu_slurp(tu_scratch("chunkd.brs"), &nb);
    EXPECT(a && b && na == nb && memcmp(a, b, na) == 0, "the chunk size changed the scene file");
    free(a);
    free(b);
    opt = build_options(100, 8, 900, 7);
    build_and_compare(&s, &source, &opt, 300, "chunks of 7");
    tu_scene_free(&s);
}

/* A mesh that fits one bucket gives the file of a whole in-memory median
** split, whatever the bucket size above it; the build is deterministic;
** the checker refuses a smaller point_tris. */
static void test_one_bucket_and_checker(void)
{
    uint64_t st = test_seed() + 16;
    tu_scene s;
    brt_mesh mesh;
    brt_scene_options opt;
    brt_scene *scene = NULL;
    brt_error err;
    unsigned char *a, *b, *c;
    size_t na = 0, nb = 0, nc = 0;
    memset(&s, 0, sizeof s);
    tu_random_soup(&s, &st, 2000, 0.02f);
    mesh = tu_mesh_view(&s);
    opt = build_options(50, 8, 0, 0);
    CHECK(brt_scene_build(&mesh, &opt, 1, tu_scratch("one1.brs"), &err) == BRT_OK, "%s", err.message);
    CHECK(brt_scene_build(&mesh, &opt, 1, tu_scratch("one2.brs"), &err) == BRT_OK, "%s", err.message);
    opt = build_options(50, 8, 4000, 0);
    CHECK(brt_scene_build(&mesh, &opt, 1, tu_scratch("one3.brs"), &err) == BRT_OK, "%s", err.message);
    a = tu_slurp(tu_scratch("one1.brs"), &na);
    b = tu_slurp(tu_scratch("one2.brs"), &nb);
    c = tu_slurp(tu_scratch("one3.brs"), &nc);
    EXPECT(a && b && na == nb && memcmp(a, b, na) == 0, "two builds differ");
    EXPECT(a && c && na == nc && memcmp(a, c, na) == 0, "one bucket of 4000 differs from the default");
    free(a);
    free(b);
    free(c);
    CHECK(brt_scene_open(tu_scratch("one1.brs"), &scene, &err) == BRT_OK, "%s", err.message);
    EXPECT(brt_scene_point_count(scene) == 40, "%u batching points, expected 40 full ones",
           brt_scene_point_count(scene));
    EXPECT(brt_scene_check_partition(scene, 50, &err) == BRT_OK, "%s", err.message);
    EXPECT(brt_scene_check_partition(scene, 49, &err) == BRT_ECHECK && strstr(err.message, "holds 50"),
           "the checker accepted 50 triangles under a limit of 49");
    brt_scene_close(scene);
    tu_scene_free(&s);
}

/* ---- failing and interrupted builds leave nothing ------------------------ */

/* A triangle source computed on the fly (no mesh in memory): n random
** triangles in chunks of 1000; it sets *flag once `after` chunks are
** emitted. */
typedef struct generator {
    uint32_t n, after;
    volatile sig_atomic_t *flag;
} generator;

static brt_result generate(const void *user, brt_triangle_fn emit, void *emit_user, brt_error *err)
{
    const generator *g = user;
    float corners[9 * 1000];
    uint64_t st = 99;
    uint32_t first, chunks = 0;
    brt_result r = BRT_OK;
    for (first = 0; first < g->n && r == BRT_OK; first += 1000) {
        uint32_t count = g->n - first < 1000 ? g->n - first : 1000, i;
        for (i = 0; i < count; i++) {
            float c[3];
            int k;
            for (k = 0; k < 3; k++) c[k] = tu_rnd(&st, 0, 100);
            for (k = 0; k < 9; k++) corners[9 * i + k] = c[k % 3] + tu_rnd(&st, -0.5f, 0.5f);
        }
        r = emit(emit_user, corners, count, first, err);
        if (g->flag && ++chunks >= g->after) *g->flag = 1;
    }
    return r;
}

static void generator_source(const generator *g, brt_triangle_source *source)
{
    source->run = generate;
    source->user = g;
}

/* Runs a build of n generated triangles in a child with a file size
** limit (SIGXFSZ ignored: writes past it fail with EFBIG); returns the
** child's result code and its message in msg. */
static int build_with_size_limit(const char *dir, uint32_t n, rlim_t limit, char msg[512])
{
    int fds[2], status;
    pid_t pid;
    ssize_t got;
    (void)test_tmpdir();
    if (pipe(fds) != 0) return -1;
    fflush(stdout);
    pid = fork();
    if (pid == 0) {
        struct rlimit rl;
        generator g;
        brt_triangle_source source;
        brt_scene_options opt = build_options(100, 8, 2000, 64);
        brt_error err;
        char path[600];
        brt_result r;
        rl.rlim_cur = rl.rlim_max = limit;
        signal(SIGXFSZ, SIG_IGN);
        setrlimit(RLIMIT_FSIZE, &rl);
        memset(&g, 0, sizeof g);
        g.n = n;
        generator_source(&g, &source);
        snprintf(path, sizeof path, "%s/scene.brs", dir);
        err.message[0] = 0;
        r = brt_scene_build_stream(&source, &opt, 1, path, &err);
        if (write(fds[1], err.message, strlen(err.message) + 1) < 0) _exit(100);
        _exit((int)r);
    }
    close(fds[1]);
    got = pid > 0 ? read(fds[0], msg, 511) : -1;
    msg[got > 0 ? got : 0] = 0;
    close(fds[0]);
    if (pid < 0 || waitpid(pid, &status, 0) != pid || !WIFEXITED(status)) return -1;
    return WEXITSTATUS(status);
}

/* File size limits from 1/10000 to 99/100 of the largest file the build
** writes (the spill file, 80 bytes per triangle here, or the scene) stop it
** in pass A, the scatter, the blobs or the tables: each is a one-line
** error naming the scene and leaves the directory empty.  Without a limit
** the same build succeeds. */
static void test_write_failure(void)
{
    static const double share[] = {0.0001, 0.25, 0.5, 0.75, 0.99};
    const char *dir = fresh_dir("full");
    char msg[512], left[256], scene[600];
    struct stat st;
    double largest = 80.0 * 12000;
    size_t i;
    CHECK(build_with_size_limit(dir, 12000, RLIM_INFINITY, msg) == BRT_OK, "unlimited: %s", msg);
    snprintf(scene, sizeof scene, "%s/scene.brs", dir);
    CHECK(stat(scene, &st) == 0 && unlink(scene) == 0, "no scene file %s", scene);
    if ((double)st.st_size > largest) largest = (double)st.st_size;
    for (i = 0; i < sizeof share / sizeof share[0]; i++) {
        rlim_t limit = (rlim_t)(share[i] * largest);
        int r = build_with_size_limit(dir, 12000, limit, msg), n = dir_entries(dir, left);
        EXPECT(r == BRT_EIO && strstr(msg, "scene.brs: cannot write: File too large") &&
                   !strchr(msg, '\n'),
               "limit %lu: result %d, '%s'", (unsigned long)limit, r, msg);
        EXPECT(n == 0, "limit %lu: %d files left, such as %s", (unsigned long)limit, n, left);
    }
}

/* ---- forged blob extents (issue 32, class 4) ----------------------------- */

/* The fixed scene of the fuzz targets with batching point 1's blob moved
** to (offset, size), every checksum repaired as a forger would: only the
** extent check of scene open stands between it and a read past the end
** (a size near 2^64 wraps offset + size; mapped, it would be SIGBUS). */
static brt_result open_with_blob_extent(const unsigned char *base, size_t size, uint64_t offset,
                                        uint64_t blob_size, brt_error *err)
{
    unsigned char *f = malloc(size);
    uint64_t entry;
    brt_scene *scene = NULL;
    brt_result r;
    if (!f) return BRT_ENOMEM;
    memcpy(f, base, size);
    entry = brt_get_le64(f + 56) + 80;              /* point table entry 1 */
    brt_put_le64(f + entry + 24, offset);
    brt_put_le64(f + entry + 32, blob_size);
    fuzz_repair_scene_checksums(f, size);
    r = tu_spill(tu_scratch("extent.brs"), f, size) ? BRT_OK : BRT_EIO;
    free(f);
    if (r == BRT_OK) r = brt_scene_open(tu_scratch("extent.brs"), &scene, err);
    brt_scene_close(scene);
    return r;
}

static void test_forged_blob_extents(void)
{
    const struct { uint64_t offset, size; const char *what; } cases[] = {
        {0, UINT64_MAX, "size 2^64-1"},
        {0, UINT64_MAX - 4095, "size 2^64-4096 (rounds up to 0 pages)"},
        {4096, 0, "offset past the end (set below)"},
        {0, 0, "size one byte past the end (set below)"},
        {1, 16, "offset not on a page"},
    };
    unsigned char *base;
    size_t size, i;
    brt_error err;
    CHECK(fuzz_fixed_scene_build(tu_scratch("extent_base.brs"), &err) == BRT_OK, "%s", err.message);
    base = tu_slurp(tu_scratch("extent_base.brs"), &size);
    CHECK(base && size >= 256 && brt_get_le32(base + 32) >= 2, "no fixed scene of 2 points");
    EXPECT(open_with_blob_extent(base, size, brt_get_le64(base + brt_get_le64(base + 56) + 104),
                                 brt_get_le64(base + brt_get_le64(base + 56) + 112), &err) == BRT_OK,
           "unforged: %s", err.message);
    for (i = 0; i < sizeof cases / sizeof cases[0]; i++) {
        uint64_t offset = cases[i].offset, blob = cases[i].size;
        brt_result r;
        if (i == 2) offset = ((uint64_t)size + 4095) / 4096 * 4096, blob = 1;
        if (i == 3) blob = (uint64_t)size + 1;
        r = open_with_blob_extent(base, size, offset, blob, &err);
        EXPECT(r == BRT_EFORMAT && strstr(err.message, "extent.brs: batching point 1: blob outside the file"),
               "%s: %s, '%s'", cases[i].what, brt_result_string(r), err.message);
    }
    free(base);
}

/* ---- the out-of-core build's own invariants (issue 32, class 5) ---------- */

/* Four clusters of 1000 small triangles, 100 apart along the diagonal
** (each one cell of the spill's Morton histogram on every axis), streamed
** round robin (triangle j in cluster j % 4); with renumber, the second
** chunk claims to start where the first did. */
typedef struct clusters {
    int renumber;
} clusters;

static brt_result emit_clusters(const void *user, brt_triangle_fn emit, void *emit_user,
                                brt_error *err)
{
    const clusters *c = user;
    float corners[9 * 1000];
    uint64_t st = 7;
    uint32_t first, i;
    brt_result r = BRT_OK;
    for (first = 0; first < 4000 && r == BRT_OK; first += 1000) {
        for (i = 0; i < 1000; i++) {
            float base = 100.0f * (float)((first + i) % 4);
            int k;
            for (k = 0; k < 9; k++) corners[9 * i + k] = base + tu_rnd(&st, 0, 1);
        }
        r = emit(emit_user, corners, 1000, c->renumber && first > 0 ? first - 1000 : first, err);
    }
    return r;
}

/* Buckets of 1000 (smaller than the 4000 triangles, so the spill splits
** the stream by its centroids) and batching points of 100: a spatial split
** gives each cluster its own bucket, so every batching point's box (read
** from the file's point table) lies in one cluster, less than 2 wide in x;
** full buckets give exactly 40 points.  A split that fell back to stream
** order would mix the clusters in every point. */
static void test_buckets_spatial_and_full(void)
{
    const char *path = tu_scratch("clusters.brs");
    brt_scene_options opt = build_options(100, 8, 1000, 0);
    brt_triangle_source source;
    clusters c = {0};
    unsigned char *f;
    size_t size;
    uint32_t n, i, wide = 0;
    brt_error err;
    source.run = emit_clusters;
    source.user = &c;
    CHECK(brt_scene_build_stream(&source, &opt, 1, path, &err) == BRT_OK, "%s", err.message);
    f = tu_slurp(path, &size);
    CHECK(f && size >= 256, "no scene file");
    n = brt_get_le32(f + 32);
    EXPECT(n == 40, "%u batching points for 4000 triangles in full buckets of 1000, expected 40", n);
    for (i = 0; i < n && brt_get_le64(f + 56) + 80 * (uint64_t)(i + 1) <= size; i++) {
        const unsigned char *e = f + brt_get_le64(f + 56) + 80 * (uint64_t)i;
        union { uint32_t u; float x; } lo, hi;
        lo.u = brt_get_le32(e);
        hi.u = brt_get_le32(e + 12);
        if (!(hi.x - lo.x < 2.0f)) wide++;
    }
    EXPECT(wide == 0, "%u of %u batching points span more than one cluster in x", wide, n);
    free(f);
}

/* A source that numbers its second chunk 0 again is refused with a
** message naming the scene and both numbers, and leaves nothing. */
static void test_misnumbered_chunks(void)
{
    const char *dir = fresh_dir("misnumbered");
    char path[600], left[256];
    brt_scene_options opt = build_options(100, 8, 1000, 0);
    brt_triangle_source source;
    clusters c = {1};
    brt_error err;
    brt_result r;
    int n;
    source.run = emit_clusters;
    source.user = &c;
    snprintf(path, sizeof path, "%s/scene.brs", dir);
    r = brt_scene_build_stream(&source, &opt, 1, path, &err);
    EXPECT(r == BRT_EARG && strstr(err.message, "scene.brs: the triangle source numbered a chunk 0, "
                                                "not 1000"), "misnumbered chunk: %s: '%s'", brt_result_string(r),
           err.message);
    n = dir_entries(dir, left);
    EXPECT(n == 0, "%d files left, such as %s", n, left);
}

/* A mesh file whose error comes after a whole chunk was spilled: the
** build returns the reader's message (as brt_mesh_load gives it) and
** leaves the directory empty. */
static void test_source_error(void)
{
    const char *bad = write_big_obj("bad_for_build.obj", 40000, 1), *dir = fresh_dir("bad_source");
    char path[600], left[256];
    brt_scene_options opt = build_options(1000, 8, 4000, 0);
    brt_triangle_source source;
    brt_error load_err, err;
    brt_mesh mesh;
    int n;
    CHECK(bad != NULL, "cannot write the OBJ file");
    CHECK(brt_mesh_load(bad, &mesh, &load_err) == BRT_EPARSE, "the bad OBJ loads");
    snprintf(path, sizeof path, "%s/scene.brs", dir);
    brt_mesh_file_source(bad, &source);
    EXPECT(brt_scene_build_stream(&source, &opt, 1, path, &err) == BRT_EPARSE &&
               strcmp(err.message, load_err.message) == 0,
           "build says '%s', load says '%s'", err.message, load_err.message);
    n = dir_entries(dir, left);
    EXPECT(n == 0, "%d files left, such as %s", n, left);
}

/* The flag set after the first chunk (pass A), after the last one (the
** first poll after pass A), and by a real SIGALRM handler at several
** times: BRT_EINTR and an empty directory. */
static volatile sig_atomic_t alarm_flag;
static void on_alarm(int sig) { (void)sig; alarm_flag = 1; }

static void test_interrupt(void)
{
    static const uint32_t after[] = {1, 20};
    static const long usec[] = {2000, 30000, 120000};
    const char *dir = fresh_dir("interrupted");
    char path[600], left[256];
    brt_scene_options opt = build_options(100, 8, 2000, 64);
    brt_triangle_source source;
    brt_error err;
    generator g;
    size_t i;
    snprintf(path, sizeof path, "%s/scene.brs", dir);
    for (i = 0; i < 2; i++) {
        volatile sig_atomic_t flag = 0;
        brt_result r;
        int n;
        g.n = 20000;
        g.after = after[i];
        g.flag = &flag;
        opt.interrupt = &flag;
        generator_source(&g, &source);
        r = brt_scene_build_stream(&source, &opt, 1, path, &err);
        n = dir_entries(dir, left);
        EXPECT(r == BRT_EINTR && strstr(err.message, "interrupted"), "after %u chunks: not interrupted: result %d %s",
               after[i], (int)r, r ? err.message : "");
        EXPECT(n == 0, "after %u chunks: %d files left, such as %s", after[i], n, left);
    }
    for (i = 0; i < sizeof usec / sizeof usec[0]; i++) {
        struct itimerval timer, off;
        brt_result r;
        int n;
        memset(&timer, 0, sizeof timer);
        memset(&off, 0, sizeof off);
        timer.it_value.tv_usec = usec[i];
        alarm_flag = 0;
        signal(SIGALRM, on_alarm);
        g.n = 400000;   /* seconds of work: the signal comes first */
        g.flag = NULL;
        opt.interrupt = &alarm_flag;
        generator_source(&g, &source);
        setitimer(ITIMER_REAL, &timer, NULL);
        r = brt_scene_build_stream(&source, &opt, 1, path, &err);
        setitimer(ITIMER_REAL, &off, NULL);
        signal(SIGALRM, SIG_DFL);
        n = dir_entries(dir, left);
        EXPECT(r == BRT_EINTR, "SIGALRM after %ld us: %d %s", usec[i], (int)r, r ? err.message : "");
        EXPECT(n == 0, "SIGALRM after %ld us: %d files left, such as %s", usec[i], n, left);
    }
}

/* ---- the memory bound ----------------------------------------------------- */

/* Peak RSS growth (kB) of a build of n generated triangles in a child
** process whose high-water mark is reset first; -1 when /proc cannot. */
static long vm_kb(const char *field)
{
    FILE *f = fopen("/proc/self/status", "r");
    char line[256];
    long kb = -1;
    size_t n = strlen(field);
    if (!f) return -1;
    while (fgets(line, sizeof line, f))
        if (strncmp(line, field, n) == 0) kb = strtol(line + n, NULL, 10);
    fclose(f);
    return kb;
}

static long build_rss_growth(uint32_t n)
{
    int fds[2], status;
    long growth = -1;
    pid_t pid;
    (void)test_tmpdir();   /* made by the parent, so the child writes there */
    if (pipe(fds) != 0) return -1;
    fflush(stdout);
    pid = fork();
    if (pid == 0) {
        generator g;
        brt_triangle_source source;
        brt_scene_options opt = build_options(500, 2, 2000, 64);
        brt_error err;
        FILE *f = fopen("/proc/self/clear_refs", "w");
        long before, after = -1;
        int reset = f && fputs("5", f) >= 0;
        if (f && fclose(f) != 0) reset = 0;
        before = vm_kb("VmRSS:");
        memset(&g, 0, sizeof g);
        g.n = n;
        generator_source(&g, &source);
        if (reset && brt_scene_build_stream(&source, &opt, 1, tu_scratch("memory.brs"), &err) == BRT_OK)
            after = vm_kb("VmHWM:");
        growth = after >= 0 && before >= 0 ? after - before : -1;
        if (write(fds[1], &growth, sizeof growth) < 0) _exit(1);
        _exit(0);
    }
    close(fds[1]);
    if (pid < 0 || read(fds[0], &growth, sizeof growth) != (ssize_t)sizeof growth) growth = -1;
    close(fds[0]);
    if (pid > 0) waitpid(pid, &status, 0);
    return growth;
}

/* 50 000 and 500 000 triangles with buckets of 2000 and spill chunks of
** 64: holding the triangles would cost 36 bytes each, 16 MiB more for the
** larger input; the build's own buffers grow only by the histogram (1 MiB
** at most below 2^21 / 4 records) and the per-point tables. */
static void test_memory_bound(void)
{
    long small, large;
    if (!tu_rss_is_meaningful()) return;
    small = build_rss_growth(50000);
    if (small < 0) {
        test_skip("cannot reset the peak RSS through /proc/self/clear_refs");
        return;
    }
    large = build_rss_growth(500000);
    CHECK(large >= 0, "the child build failed");
    EXPECT(large - small < 4096, "peak RSS grew by %ld kB for 50 000 and %ld kB for 500 000 triangles",
           small, large);
}

void suite_build(void)
{
    test_run("build: stream == load (triangles, numbers, chunks, errors)", test_stream_equals_load);
    test_run("build: batched == direct, shared meshes streamed from their files", test_shared_meshes);
    test_run("build: batched == direct, adversarial triangle sets", test_adversarial_sets);
    test_run("build: batched == direct, adversarial arrival orders", test_adversarial_order);
    test_run("build: a bucket larger than a spill chunk", test_bucket_larger_than_chunk);
    test_run("build: one bucket is the whole median split; deterministic; checker", test_one_bucket_and_checker);
    test_run("build: write failures leave nothing", test_write_failure);
    test_run("build: a bad mesh file leaves nothing", test_source_error);
    test_run("build: interrupts leave nothing", test_interrupt);
    test_run("build: forged blob extents (2^64-1, past the end, off a page)", test_forged_blob_extents);
    test_run("build: buckets are spatial and full (clusters streamed round robin)", test_buckets_spatial_and_full);
    test_run("build: a source that misnumbers its chunks is refused", test_misnumbered_chunks);
    test_run("build: memory does not grow with the triangle count", test_memory_bound);
}
