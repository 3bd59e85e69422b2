/*
** tests/test_hardening.c -- bad input, I/O faults and limits, with
** nothing lost and nothing left behind.
**
**  - the fuzz corpus (tests/corpus/NAME, seeds and every crash the fuzzers
**    of tests/fuzz/ found) replayed through the same targets, so "make
**    test" checks the regressions without clang;
**  - a table of bad inputs and impossible options run through the
**    programs, each with its exact exit status and stderr line, and no
**    output or "*.tmp.*" file left behind (tests/test_cli.c covers the
**    first cases; this table adds the rest: NaN and huge values, index
**    overflow, binary garbage, truncation, voxelize, mkscene and render);
**  - read faults injected through brt_trace_options.read_fn: EIO and end
**    of file at every call, short reads of every size, EINTR; the rays
**    finished before a fault must carry exactly the direct-mode hit;
**  - read faults on the read-ahead (two threads): a failed, short or
**    corrupt read-ahead is dropped or completed, never used, and the
**    counts stay the clean run's;
**  - write faults from a file-size limit (RLIMIT_FSIZE with SIGXFSZ
**    ignored makes write() fail with EFBIG, as a full disk fails with
**    ENOSPC), from a full device (ENOSPC) and a directory as the target:
**    the library and the programs must leave no partial file;
**  - limits: one triangle, all triangles identical, a memory limit below
**    one batching point, one ray in flight, no rays at all, a 1x1 image;
**  - forged scene files (README, "The scene file"): valid checksums, one
**    cross-reference broken per file, one file per line of the validators
**    of scene.c's scene open and bvh.c's blob open, each refused naming
**    the part: every axis, every section's extent, blobs that share a
**    page, a version-4 file's margins, prototypes and instance counts.
** Oracles: the direct mode and brute force over brt_intersect_triangle.
*/
#include "test.h"
#include "util.h"
#include "fuzz/targets.h"

#include <dirent.h>
#include <errno.h>
#include <float.h>
#include <math.h>
#include <pthread.h>
#include <signal.h>
#include <stdarg.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

/* ===================================================================== */
/* Files                                                                 */
/* ===================================================================== */

/* NAME in the scratch directory (a few rotating buffers). */
static const char *scratch(const char *name)
{
    static char paths[8][512];
    static int next;
    char *out = paths[next++ % 8];
    snprintf(out, 512, "%s/%s", test_tmpdir(), name);
    return out;
}

static int file_exists(const char *path)
{
    struct stat st;
    return stat(path, &st) == 0;
}

static int spill(const char *name, const void *data, size_t size)
{
    FILE *f = fopen(scratch(name), "wb");
    int ok = f && (size == 0 || fwrite(data, 1, size, f) == size);
    if (f && fclose(f) != 0) ok = 0;
    return ok;
}

static int spill_text(const char *name, const char *text)
{
    return spill(name, text, strlen(text));
}


/* "@" in text replaced by the scratch directory, into out. */
static void expand(const char *text, char *out, size_t size)
{
    const char *dir = test_tmpdir();
    size_t n = 0, len = strlen(dir);
    for (; *text && n + len + 1 < size; text++) {
        if (*text == '@') { memcpy(out + n, dir, len); n += len; }
        else out[n++] = *text;
    }
    out[n] = 0;
}

/* The whole of a small file, NUL-terminated, into out; "" when absent. */
static void read_small(const char *path, char *out, size_t size)
{
    FILE *f = fopen(path, "rb");
    size_t n = f ? fread(out, 1, size - 1, f) : 0;
    out[n] = 0;
    if (f) fclose(f);
}

/* Runs "$BRT_BUILD/ARGS" ('@' = scratch directory) through sh, stdout to
** run.out and stderr to run.err in the scratch directory.  With
** fsize_blocks >= 0 the program runs under "ulimit -f" (512-byte blocks)
** with SIGXFSZ ignored, so a write past the limit fails with EFBIG, as
** one onto a full disk fails with ENOSPC.  Returns the exit status, or -1
** when the program died from a signal. */
static int run(long fsize_blocks, const char *args)
{
    char expanded[4096], limit[64] = "", cmd[8192];
    const char *build = getenv("BRT_BUILD");
    int status;
    expand(args, expanded, sizeof expanded);
    if (fsize_blocks >= 0)
        snprintf(limit, sizeof limit, "trap '' XFSZ; ulimit -f %ld; exec ", fsize_blocks);
    snprintf(cmd, sizeof cmd, "%s%s/%s > '%s' 2> '%s'", limit, build ? build : "build",
             expanded, scratch("run.out"), scratch("run.err"));
    status = system(cmd);
    if (status == -1 || !WIFEXITED(status)) return -1;
    return WEXITSTATUS(status);
}

/* ===================================================================== */
/* The fuzz corpus                                                       */
/* ===================================================================== */

static void report_problem(const char *file, const char *problem, void *user)
{
    (void)user;
    test_fail_at(__FILE__, __LINE__, "%s: %s", file, problem);
}

static void test_corpus_replay(void)
{
    const fuzz_target *t;
    for (t = fuzz_targets; t->name; t++) {
        char dir[64];
        long n;
        snprintf(dir, sizeof dir, "tests/corpus/%s", t->name);
        n = fuzz_replay(t, dir, report_problem, NULL);
        if (n < 0) {
            test_skip("%s not found (run from the repository's top folder)", dir);
            return;
        }
        EXPECT(n > 0, "%s is empty", dir);
    }
}

/* The scene target repairs checksums before opening; an intact seed must
** come through unchanged and trace, or the fuzzer never gets past the
** checksums (its copy of checksum64 would have drifted from base.c). */
static void test_scene_seed(void)
{
    const char *seed = "tests/corpus/scene/fixed.brs";
    const fuzz_target *target = fuzz_find("scene");
    brt_scene *scene = NULL;
    brt_error err;
    brt_mesh mesh;
    if (!file_exists(seed)) {
        test_skip("%s not found (run from the repository's top folder)", seed);
        return;
    }
    CHECK(brt_scene_open(seed, &scene, &err) == BRT_OK, "%s (rebuild the seed with "
          "fuzz_fixed_scene_build when the format changes)", err.message);
    fuzz_fixed_mesh(&mesh);
    EXPECT(brt_scene_triangle_count(scene) == mesh.triangle_count, "the seed is not the fixed mesh");
    brt_scene_close(scene);
    CHECK(target != NULL, "no scene target");
    CHECK(fuzz_replay(target, seed, report_problem, NULL) == 1, "seed not replayed");
}

/* ===================================================================== */
/* Bad input through the programs                                        */
/* ===================================================================== */

/* One run: its exact exit status and stderr ('@' is the scratch
** directory), and a file it must not leave behind. */
typedef struct bad_run {
    const char *args;
    int status;
    const char *message;   /* the whole stderr, newline added */
    const char *output;    /* NULL when the run names no output */
} bad_run;

static const bad_run bad_runs[] = {
    /* meshes */
    {"trace @/nan.obj @/good.rays @/b1.hits", 1,
     "trace: @/nan.obj:2: coordinate 'nan' is not finite", "b1.hits"},
    {"trace @/inf.obj @/good.rays @/b2.hits --batched --scene @/b2.brs", 1,
     "trace: @/inf.obj:3: coordinate '-1e39' is not finite", "b2.hits"},
    {"trace @/negative.obj @/good.rays @/b3.hits", 1,
     "trace: @/negative.obj:4: vertex index -4 out of range (3 vertices so far)", "b3.hits"},
    {"trace @/wrap.obj @/good.rays @/b4.hits", 1,
     "trace: @/wrap.obj:4: vertex index 4294967297 out of range (3 vertices so far)", "b4.hits"},
    {"trace @/text.obj @/good.rays @/b5.hits", 1, "trace: @/text.obj:2: bad number 'one'",
     "b5.hits"},
    {"trace @/garbage.obj @/good.rays @/b6.hits", 1,
     "trace: @/garbage.obj:1: unknown statement '?????\?'", "b6.hits"},
    {"trace @/cut.obj @/good.rays @/b7.hits", 1,
     "trace: @/cut.obj:2: vertex needs 3 coordinates, has 1", "b7.hits"},
    {"trace @/points.obj @/good.rays @/b8.hits --batched --scene @/b8.brs", 1,
     "trace: @/points.obj: no triangles", "b8.hits"},
    {"trace @/huge.ply @/good.rays @/b9.hits", 1,
     "trace: @/huge.ply:3: bad PLY header: a second vertex element or too many vertices",
     "b9.hits"},
    {"trace @/version.ply @/good.rays @/b10.hits", 1,
     "trace: @/version.ply:2: bad PLY header: unknown format", "b10.hits"},
    {"trace @/cut.ply @/good.rays @/b11.hits", 1,
     "trace: @/cut.ply: element face 0: file truncated", "b11.hits"},
    {"voxelize @/nan.obj --stats @/b12.json --out @/b12.png", 1,
     "voxelize: @/nan.obj:2: coordinate 'nan' is not finite", "b12.json"},
    {"voxelize @/points.obj --out @/b13.png", 1, "voxelize: @/points.obj: no triangles",
     "b13.png"},
    {"raygen @/garbage.obj @/b14.rays --kind camera", 1,
     "raygen: @/garbage.obj:1: unknown statement '?????\?'", "b14.rays"},
    /* ray and scene files */
    {"trace @/tri.obj @/odd.rays @/b15.hits --batched --scene @/b15.brs", 1,
     "trace: @/odd.rays: size 65 is not a multiple of the 32-byte ray record", "b15.hits"},
    {"trace @/tri.obj @/good.rays @/b16.hits --batched --scene @/version.brs", 1,
     "trace: @/version.brs: scene file version 2, this build reads versions 3 and 4 (delete the "
     "file to rebuild it)", "b16.hits"},
    /* option values */
    {"trace @/tri.obj @/good.rays @/b17.hits --proxy-res 0", 1,
     "trace: --proxy-res: expected an integer in 2..1024, got '0'", "b17.hits"},
    {"trace @/tri.obj @/good.rays @/b18.hits --proxy-res -4", 1,
     "trace: --proxy-res: expected an integer in 2..1024, got '-4'", "b18.hits"},
    {"trace @/tri.obj @/good.rays @/b19.hits --memory -5", 1,
     "trace: --memory: expected a size above 0 such as 512M (suffix K, M or G), got '-5'",
     "b19.hits"},
    {"trace @/tri.obj @/good.rays @/b20.hits --memory 0K", 1,
     "trace: --memory: expected a size above 0 such as 512M (suffix K, M or G), got '0K'",
     "b20.hits"},
    {"trace @/tri.obj @/good.rays @/b21.hits --memory 99999999999G", 1,
     "trace: --memory: expected a size above 0 such as 512M (suffix K, M or G), got "
     "'99999999999G'", "b21.hits"},
    {"trace @/tri.obj @/good.rays @/b22.hits --point-tris -1", 1,
     "trace: --point-tris: expected an integer in 1..4294967295, got '-1'", "b22.hits"},
    {"trace @/tri.obj @/good.rays @/b23.hits --point-tris 4294967296", 1,
     "trace: --point-tris: expected an integer in 1..4294967295, got '4294967296'", "b23.hits"},
    {"trace @/tri.obj @/good.rays @/b24.hits --stats @/no_such_dir/b24.json", 1,
     "trace: @/no_such_dir/b24.json: cannot create: No such file or directory", "b24.hits"},
    {"raygen @/tri.obj @/b25.rays --kind random --count 4294967296", 1,
     "raygen: --count: expected an integer in 1..4294967295, got '4294967296'", "b25.rays"},
    {"raygen @/tri.obj @/b26.rays --kind random --count 1e3", 1,
     "raygen: --count: expected an integer in 1..4294967295, got '1e3'", "b26.rays"},
    {"raygen @/tri.obj @/b27.rays --kind random --seed -1", 1,
     "raygen: --seed: expected an integer in 0..18446744073709551615, got '-1'", "b27.rays"},
    {"hitdiff @/good.hits @/good.hits --t-rel -1", 1,
     "hitdiff: --t-rel: expected a number in 0..2, got '-1'", NULL},
    {"hitdiff @/good.hits @/good.hits --max-disagree inf", 1,
     "hitdiff: --max-disagree: expected a number in 0..1, got 'inf'", NULL},
    {"voxelize @/tri.obj --proxy-res 0", 1, "voxelize: --proxy-res: expected an integer in 2..1024, got '0'",
     NULL},
    {"voxelize @/tri.obj --proxy-res -2", 1,
     "voxelize: --proxy-res: expected an integer in 2..1024, got '-2'", NULL},
    {"voxelize @/tri.obj --proxy-res 3 --out @/b28.png", 1,
     "voxelize: --proxy-res: expected a power of two in 2..1024, got '3'", "b28.png"},
    {"voxelize @/tri.obj --size 0 --out @/b29.png", 1,
     "voxelize: --size: expected an integer in 16..4096, got '0'", "b29.png"},
    {"voxelize @/tri.obj --stats @/b30.json --out @/no_such_dir/b30.png", 1,
     "voxelize: @/no_such_dir/b30.png: cannot create: No such file or directory", "b30.json"},
    {"voxelize @/tri.obj --frobnicate", 1, "voxelize: unknown option '--frobnicate' (see --help)",
     NULL},
    {"voxelize @/missing.obj --stats @/b31.json", 1,
     "voxelize: @/missing.obj: cannot open: No such file or directory", "b31.json"},
    {"voxelize", 1, "voxelize: expected MESH (see --help)", NULL},
    {"mkscene crown @/b32.ply --scale 0", 1,
     "mkscene: --scale: expected a number in 0.001..10000, got '0'", "b32.ply"},
    {"mkscene crown @/b33.ply --scale -1", 1,
     "mkscene: --scale: expected a number in 0.001..10000, got '-1'", "b33.ply"},
    {"mkscene crown @/b34.ply --scale nan", 1,
     "mkscene: --scale: expected a number in 0.001..10000, got 'nan'", "b34.ply"},
    {"mkscene crown @/b35.ply --scale 1e9", 1,
     "mkscene: --scale: expected a number in 0.001..10000, got '1e9'", "b35.ply"},
    {"mkscene crown @/b36.ply --seed -1", 1,
     "mkscene: --seed: expected an integer in 0..18446744073709551615, got '-1'", "b36.ply"},
    {"mkscene teapot @/b37.ply", 1,
     "mkscene: unknown scene 'teapot' (built-in: crown, landscape, island)", "b37.ply"},
    {"mkscene crown @/b38.stl", 1, "mkscene: @/b38.stl: the output name must end in .ply, .obj or .pbrt",
     "b38.stl"},
    {"mkscene crown @/no_such_dir/b39.ply --scale 0.001", 1,
     "mkscene: @/no_such_dir/b39.ply: cannot create: No such file or directory", NULL},
    {"mkscene crown @/b40.ply --seed", 1, "mkscene: --seed needs a value (see --help)", "b40.ply"},
    {"mkscene landscape @/b40a.ply --scale 200", 1, "mkscene: landscape: scale 200 baked needs more "
     "than 2^32 - 1 vertices or triangles (a .pbrt file keeps the instances)", "b40a.ply"},
    {"mkscene crown", 1, "mkscene: expected NAME and OUT.ply|OUT.obj (see --help)", NULL},
    {"render crown --scale 0.01 --spp 0 --out @/b41.png", 1,
     "render: --spp: expected an integer in 1..65536, got '0'", "b41.png"},
    {"render crown --scale 0.01 --width 0 --out @/b42.png", 1,
     "render: --width: expected an integer in 1..16384, got '0'", "b42.png"},
    {"render crown --scale 0.01 --height -3 --out @/b43.png", 1,
     "render: --height: expected an integer in 1..16384, got '-3'", "b43.png"},
    {"render crown --scale 0.01 --rays-in-flight 0 --out @/b44.png", 1,
     "render: --rays-in-flight: expected an integer in 1..67108864, got '0'", "b44.png"},
    {"render @/nan.obj --scene @/b45.brs --out @/b45.png", 1,
     "render: @/nan.obj:2: coordinate 'nan' is not finite", "b45.png"},
};

/* A binary PLY (one triangle) cut inside its face record. */
static int write_cut_ply(void)
{
    static const char header[] = "ply\nformat binary_little_endian 1.0\nelement vertex 3\n"
                                 "property float x\nproperty float y\nproperty float z\n"
                                 "element face 1\nproperty list uchar int vertex_indices\n"
                                 "end_header\n";
    unsigned char data[sizeof header + 36 + 6];
    memset(data, 0, sizeof data);
    memcpy(data, header, sizeof header - 1);
    data[sizeof header - 1 + 36] = 3;   /* the face's count; 5 of its 12 index bytes follow */
    return spill("cut.ply", data, sizeof header - 1 + 36 + 6);
}

/* A scene file whose version field says 2, the format before inner
** proxies (the header checksum is not reached: the version is checked
** first). */
static int write_version_scene(void)
{
    brt_error err;
    FILE *f;
    unsigned char one[4] = {2, 0, 0, 0};
    int ok = fuzz_fixed_scene_build(scratch("version.brs"), &err) == BRT_OK
             && (f = fopen(scratch("version.brs"), "r+b")) != NULL;
    if (!ok) return 0;
    ok = fseek(f, 8, SEEK_SET) == 0 && fwrite(one, 1, 4, f) == 4;
    return fclose(f) == 0 && ok;
}

/* The inputs of the table and of the write-fault tests. */
static int write_bad_inputs(void)
{
    static const unsigned char garbage[] = {0x01, 0xFF, 0x80, 0x7F, 0x1B, 0x00,
                                            ' ', 'x', '\n', 0xC3, 0x28};
    static const unsigned char odd[65] = {0};
    int ok = spill_text("tri.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
             && spill_text("nan.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
             && spill_text("inf.obj", "v 0 0 0\nv 1 0 0\nv 0 -1e39 0\nf 1 2 3\n")
             && spill_text("negative.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n")
             /* 2^32 + 1: a 32-bit truncation would make it vertex 1 */
             && spill_text("wrap.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4294967297\n")
             && spill_text("text.obj", "v 0 0 0\nv one 0 0\nv 0 1 0\nf 1 2 3\n")
             && spill("garbage.obj", garbage, sizeof garbage)
             && spill_text("cut.obj", "v 0 0 0\nv 1")
             && spill_text("points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n")
             && spill_text("huge.ply", "ply\nformat binary_little_endian 1.0\n"
                           "element vertex 4294967296\nproperty float x\nproperty float y\n"
                           "property float z\nend_header\n")
             && spill_text("version.ply", "ply\nformat ascii 2.0\nend_header\n")
             && write_cut_ply() && write_version_scene() && spill("odd.rays", odd, sizeof odd)
             && spill("empty.rays", "", 0);
    return ok && run(-1, "raygen @/tri.obj @/good.rays --kind camera --count 50") == 0
           && run(-1, "trace @/tri.obj @/good.rays @/good.hits") == 0;
}

static void expect_run(const bad_run *c, long fsize_blocks)
{
    char expected[2048], got[2048], output[1024];
    int status = run(fsize_blocks, c->args);
    expand(c->message, expected, sizeof expected - 1);
    strcat(expected, "\n");
    read_small(scratch("run.err"), got, sizeof got);
    EXPECT(status == c->status, "'%s': exit status %d, expected %d", c->args, status, c->status);
    EXPECT(strcmp(got, expected) == 0, "'%s': stderr\n  '%s'\nexpected\n  '%s'", c->args, got,
           expected);
    if (c->output) {
        expand("@/", output, sizeof output - strlen(c->output));
        strcat(output, c->output);
        EXPECT(!file_exists(output), "'%s' left %s behind", c->args, c->output);
    }
    EXPECT(!tu_temporary_file_left(), "'%s' left a *.tmp.* file behind", c->args);
}

static void test_bad_runs(void)
{
    size_t i;
    CHECK(write_bad_inputs(), "cannot write the inputs");
    for (i = 0; i < sizeof bad_runs / sizeof *bad_runs; i++) expect_run(&bad_runs[i], -1);
}

/* An empty ray file is no error: no rays, an empty hit file, both modes. */
static void test_empty_ray_file(void)
{
    static const char *const modes[] = {"--direct", "--batched --scene @/empty.brs"};
    int i;
    CHECK(write_bad_inputs(), "cannot write the inputs");
    for (i = 0; i < 2; i++) {
        char args[256], hits[600];
        struct stat st;
        int status;
        snprintf(args, sizeof args, "trace @/tri.obj @/empty.rays @/empty.hits %s", modes[i]);
        status = run(-1, args);
        expand("@/empty.hits", hits, sizeof hits);
        EXPECT(status == 0, "'%s': exit status %d", args, status);
        EXPECT(stat(hits, &st) == 0 && st.st_size == 0, "'%s': no empty hit file", args);
        unlink(hits);
    }
}

/* A 1x1 image: the direct mode, and the batched one at its limits (one
** triangle per batching point, 2^3 proxies, 1 byte of memory, one path in
** flight), write the same PNG bytes. */
static void test_one_pixel_render(void)
{
    static const char *const modes[] = {
        "--direct", "--point-tris 1 --proxy-res 2 --memory 1 --rays-in-flight 1 --scene @/px1.brs",
        "--no-proxy --scene @/px2.brs"};
    char *first = NULL, *png = NULL;
    int i;
    for (i = 0; i < 3 && !test_failed(); i++) {
        char args[256], path[600];
        FILE *f;
        long n = 0;
        snprintf(args, sizeof args, "render crown --scale 0.01 --width 1 --height 1 --spp 16 "
                 "%s --out @/px.png", modes[i]);
        EXPECT(run(-1, args) == 0, "'%s' failed", args);
        expand("@/px.png", path, sizeof path);
        png = calloc(4096, 1);
        if (png && (f = fopen(path, "rb")) != NULL) {
            n = (long)fread(png, 1, 4096, f);
            fclose(f);
        }
        EXPECT(n > 8 && (!first || memcmp(first, png, 4096) == 0), "'%s': a PNG of %ld bytes, "
               "%s", args, n, first ? "unlike the direct one" : "too short");
        if (!first) first = png;
        else free(png);
    }
    free(first);
}

/* ===================================================================== */
/* Scenes and rays for the fault and limit tests                         */
/* ===================================================================== */

typedef struct bench {
    tu_scene mesh;
    brt_ray *rays;
    brt_hit *direct;    /* brt_bvh_intersect over the whole mesh */
    size_t count;
    brt_scene *scene;
} bench;

/* Rays of the four kinds of util.h and their direct-mode hits. */
static int bench_rays(bench *b, size_t per_kind, uint64_t seed)
{
    brt_bvh *bvh = NULL;
    float lo[3], hi[3];
    size_t i;
    int kind;
    tu_scene_bounds(&b->mesh, lo, hi);
    b->count = per_kind * TU_RAY_KINDS;
    b->rays = malloc(b->count * sizeof *b->rays);
    b->direct = malloc(b->count * sizeof *b->direct);
    if (!b->rays || !b->direct
        || brt_bvh_build(b->mesh.pos, b->mesh.idx, b->mesh.tcount, NULL, &bvh) != BRT_OK)
        return 0;
    for (kind = 0; kind < TU_RAY_KINDS; kind++)
        for (i = 0; i < per_kind; i++)
            tu_make_ray(&b->mesh, lo, hi, kind, &seed, &b->rays[(size_t)kind * per_kind + i]);
    for (i = 0; i < b->count; i++) {
        brt_hit_clear(&b->direct[i]);
        brt_bvh_intersect(bvh, &b->rays[i], &b->direct[i]);
    }
    brt_bvh_free(bvh);
    return 1;
}

static int bench_scene(bench *b, uint32_t point_tris, uint32_t res, const char *name)
{
    brt_scene_close(b->scene);
    b->scene = tu_build_scene(&b->mesh, point_tris, res, 0, scratch(name));
    return b->scene != NULL;
}

static void bench_free(bench *b)
{
    brt_scene_close(b->scene);
    tu_scene_free(&b->mesh);
    free(b->rays);
    free(b->direct);
    memset(b, 0, sizeof *b);
}

/* The stream: rays in order, tag = index; records which finished. */
typedef struct stream {
    const bench *b;
    brt_hit *hits;
    unsigned char *done;
    size_t next, finished, wrong;
} stream;

static size_t stream_next(void *user, brt_ray *rays, uint64_t *tags, size_t max)
{
    stream *s = user;
    size_t n = 0;
    while (n < max && s->next < s->b->count) {
        rays[n] = s->b->rays[s->next];
        tags[n++] = s->next++;
    }
    return n;
}

static void stream_finished(void *user, const brt_ray *ray, const brt_hit *hit,
                            const float normal[3], uint32_t visits, uint64_t tag)
{
    stream *s = user;
    (void)ray;
    (void)normal;
    (void)visits;
    s->hits[tag] = *hit;
    s->done[tag]++;
    s->finished++;
    if (memcmp(hit, &s->b->direct[tag], sizeof *hit) != 0) s->wrong++;
}

/* Streams every ray of b; *s tells which finished, and how many wrongly. */
static brt_result trace_stream(const bench *b, const brt_trace_options *opt, stream *s,
                               brt_error *err)
{
    brt_ray_source source;
    memset(s, 0, sizeof *s);
    s->b = b;
    s->hits = calloc(b->count, sizeof *s->hits);
    s->done = calloc(b->count, 1);
    if (!s->hits || !s->done) return BRT_ENOMEM;
    source.next_rays = stream_next;
    source.finished = stream_finished;
    source.user = s;
    return brt_scene_trace_stream(b->scene, opt, &source, NULL, err);
}

static void stream_free(stream *s)
{
    free(s->hits);
    free(s->done);
}

/* Traces all rays with opt and compares every hit with the direct mode. */
static int trace_equals_direct(const bench *b, const brt_trace_options *opt, brt_stats *stats,
                               const char *what)
{
    brt_hit *hits = malloc((b->count ? b->count : 1) * sizeof *hits);
    brt_error err;
    size_t i;
    brt_result r = hits ? brt_scene_trace(b->scene, opt, b->rays, b->count, hits, stats, &err)
                        : BRT_ENOMEM;
    int ok = r == BRT_OK;
    if (!ok) test_fail_at(__FILE__, __LINE__, "%s: %s", what, err.message);
    for (i = 0; ok && i < b->count; i++)
        if (memcmp(&hits[i], &b->direct[i], sizeof *hits) != 0) {
            test_fail_at(__FILE__, __LINE__, "%s: ray %zu: t=%a prim %u, direct t=%a prim %u",
                         what, i, hits[i].t, (unsigned)hits[i].prim, b->direct[i].t,
                         (unsigned)b->direct[i].prim);
            ok = 0;
        }
    free(hits);
    return ok;
}

/* ===================================================================== */
/* Read faults                                                           */
/* ===================================================================== */

typedef struct read_plan {
    long calls;
    long fault_at;      /* the call that fails; -1 never */
    int fault;          /* its errno, or 0: it returns 0 (end of file) */
    size_t chunk;       /* each call reads at most this (0: no limit) */
    int eintr;          /* every other call fails with EINTR first */
} read_plan;

static long planned_read(int fd, void *buf, size_t size, uint64_t offset, void *user)
{
    read_plan *p = user;
    long call = p->calls++;
    if (call == p->fault_at) {
        if (p->fault == 0) return 0;
        errno = p->fault;
        return -1;
    }
    if (p->eintr && call % 2 == 0) {
        errno = EINTR;
        return -1;
    }
    if (p->chunk && size > p->chunk) size = p->chunk;
    return (long)pread(fd, buf, size, (off_t)offset);
}

static void fault_options(brt_trace_options *opt, read_plan *plan)
{
    memset(opt, 0, sizeof *opt);
    opt->read_fn = planned_read;
    opt->read_user = plan;
    opt->memory_limit = 16 << 10;   /* reloads: the faults hit loads again and again */
    opt->rays_in_flight = 50;
    opt->threads = 1;   /* the plan counts calls: no read-ahead */
}

/* 600 triangles in 15 batching points and 400 rays. */
static int fault_bench(bench *b)
{
    uint64_t st = test_seed() + 71;
    memset(b, 0, sizeof *b);
    tu_random_soup(&b->mesh, &st, 600, 0.06f);
    return bench_rays(b, 100, st) && bench_scene(b, 40, 8, "faults.brs");
}

/* EIO (or an early end of file) at call k, for every k a trace makes:
** the trace stops with a clear error, every ray finished before the
** fault carries exactly its direct-mode hit, and none finishes twice. */
static void test_read_fault_every_call(void)
{
    static const int faults[] = {EIO, 0};
    bench b;
    brt_trace_options opt;
    read_plan plan;
    stream s;
    brt_error err;
    long k, calls;
    int f;
    size_t i;
    CHECK(fault_bench(&b), "cannot build the bench");
    memset(&plan, 0, sizeof plan);
    plan.fault_at = -1;
    fault_options(&opt, &plan);
    EXPECT(trace_stream(&b, &opt, &s, &err) == BRT_OK && s.wrong == 0 && s.finished == b.count,
           "clean run: %zu of %zu finished, %zu wrong", s.finished, b.count, s.wrong);
    stream_free(&s);
    calls = plan.calls;
    EXPECT(calls > 20, "only %ld reads: the faults would test little", calls);
    for (f = 0; f < 2 && !test_failed(); f++)
        for (k = 0; k < calls && !test_failed(); k++) {
            brt_result r;
            memset(&plan, 0, sizeof plan);
            plan.fault_at = k;
            plan.fault = faults[f];
            err.message[0] = 0;
            r = trace_stream(&b, &opt, &s, &err);
            EXPECT(f == 0 ? r == BRT_EIO : r == BRT_EFORMAT, "%s at read %ld: result %s",
                   f == 0 ? "EIO" : "end of file", k, brt_result_string(r));
            EXPECT(strstr(err.message, "faults.brs")
                   && strstr(err.message, f == 0 ? strerror(EIO) : "truncated"),
                   "%s at read %ld: message '%s'", f == 0 ? "EIO" : "end of file", k,
                   err.message);
            EXPECT(s.wrong == 0, "fault at read %ld: %zu finished rays have a wrong hit", k,
                   s.wrong);
            for (i = 0; i < b.count; i++)
                EXPECT(s.done[i] <= 1, "ray %zu finished %d times", i, s.done[i]);
            stream_free(&s);
        }
    bench_free(&b);
}

/* Reads of at most 1..40 bytes (and around a page), with EINTR before
** every other one: the same bytes, so the same hits. */
static void test_short_reads_every_size(void)
{
    static const size_t big[] = {511, 4095, 4096, 4097, 65537};
    bench b;
    brt_trace_options opt;
    read_plan plan;
    size_t chunk;
    CHECK(fault_bench(&b), "cannot build the bench");
    fault_options(&opt, &plan);
    for (chunk = 1; chunk <= 40 + sizeof big / sizeof *big && !test_failed(); chunk++) {
        char what[64];
        memset(&plan, 0, sizeof plan);
        plan.fault_at = -1;
        plan.chunk = chunk <= 40 ? chunk : big[chunk - 41];
        plan.eintr = chunk % 2;
        snprintf(what, sizeof what, "reads of at most %zu bytes%s", plan.chunk,
                 plan.eintr ? ", EINTR" : "");
        trace_equals_direct(&b, &opt, NULL, what);
    }
    bench_free(&b);
}

/* ===================================================================== */
/* Write faults: a file-size limit                                       */
/* ===================================================================== */

/* Runs fn under a file-size limit of `bytes` with SIGXFSZ ignored, then
** restores both. */
static brt_result with_file_limit(uint64_t bytes, brt_result (*fn)(void *), void *arg)
{
    struct rlimit old, lim;
    void (*old_handler)(int);
    brt_result r;
    if (getrlimit(RLIMIT_FSIZE, &old) != 0) return BRT_EARG;
    lim = old;
    lim.rlim_cur = (rlim_t)bytes;
    old_handler = signal(SIGXFSZ, SIG_IGN);
    if (setrlimit(RLIMIT_FSIZE, &lim) != 0) {
        signal(SIGXFSZ, old_handler);
        return BRT_EARG;
    }
    r = fn(arg);
    setrlimit(RLIMIT_FSIZE, &old);
    signal(SIGXFSZ, old_handler);
    return r;
}

typedef struct build_job {
    const brt_mesh *mesh;
    const char *path;
    brt_error err;
} build_job;

static brt_result build_scene(void *arg)
{
    build_job *job = arg;
    brt_scene_options opt;
    memset(&opt, 0, sizeof opt);
    opt.point_tris = 50;
    opt.proxy_res = 8;
    return brt_scene_build(job->mesh, &opt, 1, job->path, &job->err);
}

static brt_result write_rays(void *arg)
{
    build_job *job = arg;
    brt_ray rays[100];
    memset(rays, 0, sizeof rays);
    return brt_rays_write(job->path, rays, 100, &job->err);
}

/* Building a scene file, or writing a ray file, past the limit: BRT_EIO
** naming the file and EFBIG, and no file at all, final or temporary;
** exactly at the file's size it fits. */
static void test_write_faults(void)
{
    tu_scene soup = {0};
    brt_mesh mesh;
    build_job job;
    struct stat st;
    uint64_t st_seed = test_seed() + 72, size, limits[6];
    brt_result r;
    int i;
    tu_random_soup(&soup, &st_seed, 300, 0.1f);
    mesh = tu_mesh_view(&soup);
    job.mesh = &mesh;
    job.path = scratch("full.brs");
    CHECK(build_scene(&job) == BRT_OK && stat(job.path, &st) == 0, "%s", job.err.message);
    size = (uint64_t)st.st_size;
    CHECK(unlink(job.path) == 0, "cannot remove %s", job.path);
    limits[0] = 0; limits[1] = 1; limits[2] = 255; limits[3] = 4096; limits[4] = size / 2;
    limits[5] = size - 1;
    for (i = 0; i < 6; i++) {
        r = with_file_limit(limits[i], build_scene, &job);
        EXPECT(r == BRT_EIO && strstr(job.err.message, job.path)
               && strstr(job.err.message, strerror(EFBIG)),
               "scene file (%llu bytes) under a limit of %llu: result %s, '%s'",
               (unsigned long long)size, (unsigned long long)limits[i], brt_result_string(r),
               job.err.message);
        EXPECT(!file_exists(job.path) && !tu_temporary_file_left(),
               "a limit of %llu bytes left a file behind", (unsigned long long)limits[i]);
    }
    EXPECT(with_file_limit(size, build_scene, &job) == BRT_OK, "exactly %llu bytes: %s",
           (unsigned long long)size, job.err.message);
    job.path = scratch("full.rays");
    r = with_file_limit(1000, write_rays, &job);
    EXPECT(r == BRT_EIO && strstr(job.err.message, strerror(EFBIG)) && !file_exists(job.path)
           && !tu_temporary_file_left(), "3200 bytes of rays under a limit of 1000: '%s'",
           job.err.message);
    tu_scene_free(&soup);
}

/* The programs under "ulimit -f": exit 1, one clear line, no file. */
static const bad_run full_disk_runs[] = {
    {"mkscene crown @/f1.obj --scale 0.01", 1, "mkscene: @/f1.obj: cannot write: File too large",
     "f1.obj"},
    {"mkscene crown @/f2.ply --scale 0.01", 1, "mkscene: @/f2.ply: cannot write: File too large",
     "f2.ply"},
    {"trace @/tri.obj @/good.rays @/f3.hits", 1, "trace: @/f3.hits: cannot write: File too large",
     "f3.hits"},
    {"trace @/tri.obj @/good.rays @/f4.hits --batched --scene @/f4.brs", 1,
     "trace: @/f4.brs: cannot write: File too large", "f4.brs"},
    {"raygen @/tri.obj @/f5.rays --kind random --count 1000", 1,
     "raygen: @/f5.rays: cannot write: File too large", "f5.rays"},
    {"voxelize @/tri.obj --proxy-res 4 --out @/f6.png", 1,
     "voxelize: @/f6.png: cannot write: File too large", "f6.png"},
    {"render crown --scale 0.01 --width 64 --height 64 --spp 1 --direct --out @/f7.png", 1,
     "render: @/f7.png: cannot write: File too large", "f7.png"},
    {"render crown --scale 0.01 --width 64 --height 64 --spp 1 --scene @/f8.brs --out @/f8.png",
     1, "render: @/f8.brs: cannot write: File too large", "f8.brs"},
};

static void test_full_disk_programs(void)
{
    size_t i;
    CHECK(write_bad_inputs(), "cannot write the inputs");
    for (i = 0; i < sizeof full_disk_runs / sizeof *full_disk_runs; i++)
        expect_run(&full_disk_runs[i], 1);   /* 512 bytes */
}


/* ===================================================================== */
/* Faults on the read-ahead and on the last steps of a write             */
/* ===================================================================== */

/* The reader of a threaded trace: reads made by the cache's read-ahead
** thread (any thread but the one that started the trace) fail as
** planned; the others are plain preads.  (The read-ahead is the one
** reader off the calling thread: batchrt.h, brt_read_fn.) */
typedef struct ahead_plan {
    pthread_t caller;
    int mode;           /* 0 clean, 1 EIO, 2 end of file, 3 a byte flipped, 4 short */
    long ahead_calls;   /* reads made by the read-ahead thread */
} ahead_plan;

static long ahead_read(int fd, void *buf, size_t size, uint64_t offset, void *user)
{
    ahead_plan *p = user;
    long n;
    if (pthread_equal(pthread_self(), p->caller)) return (long)pread(fd, buf, size, (off_t)offset);
    p->ahead_calls++;
    if (p->mode == 1) {
        errno = EIO;
        return -1;
    }
    if (p->mode == 2) return 0;
    n = (long)pread(fd, buf, p->mode == 4 && size > 1 ? size / 2 : size, (off_t)offset);
    if (p->mode == 3 && n > 100) ((unsigned char *)buf)[100] ^= 0x40;
    return n;
}

/* A failed read-ahead is dropped and the blob read again, never used: EIO,
** an end of file or a corrupt byte on every read-ahead leave the hits the
** direct mode's and the loads and bytes read the clean run's (a dropped
** read-ahead is not counted); short read-aheads are completed. */
static void test_read_ahead_faults(void)
{
    static const char *const name[] = {"clean", "EIO", "end of file", "a flipped byte", "short reads"};
    bench b;
    brt_trace_options opt;
    brt_stats clean, st;
    ahead_plan plan;
    int mode;
    CHECK(fault_bench(&b), "cannot build the bench");
    fault_options(&opt, NULL);
    opt.read_fn = ahead_read;
    opt.read_user = &plan;
    opt.threads = 2;            /* a thread reads ahead */
    for (mode = 0; mode < 5 && !test_failed(); mode++) {
        char what[64];
        memset(&plan, 0, sizeof plan);
        plan.caller = pthread_self();
        plan.mode = mode;
        snprintf(what, sizeof what, "read-ahead with %s", name[mode]);
        if (!trace_equals_direct(&b, &opt, mode ? &st : &clean, what)) break;
        EXPECT(plan.ahead_calls > 5, "%s: only %ld reads ahead: the test is blind", what, plan.ahead_calls);
        if (mode == 0) continue;
        EXPECT(st.batch_loads == clean.batch_loads && st.disk_bytes_read == clean.disk_bytes_read,
               "%s: %llu loads, %llu bytes; clean %llu and %llu", what, (unsigned long long)st.batch_loads,
               (unsigned long long)st.disk_bytes_read, (unsigned long long)clean.batch_loads,
               (unsigned long long)clean.disk_bytes_read);
    }
    bench_free(&b);
}

/* A reader that notes two calls at once: each call stays inside a while
** (the read-ahead's longer), so that a read the scheduler makes while the
** read-ahead still reads would be seen. */
typedef struct overlap_reader {
    pthread_mutex_t lock;
    pthread_t caller;
    int inside, overlaps;
    long calls;
} overlap_reader;

static long overlap_read(int fd, void *buf, size_t size, uint64_t offset, void *user)
{
    overlap_reader *o = user;
    long n;
    pthread_mutex_lock(&o->lock);
    o->overlaps += o->inside > 0;
    o->inside++;
    o->calls++;
    pthread_mutex_unlock(&o->lock);
    tu_sleep_ms(pthread_equal(pthread_self(), o->caller) ? 1 : 4);
    n = (long)pread(fd, buf, size, (off_t)offset);
    pthread_mutex_lock(&o->lock);
    o->inside--;
    pthread_mutex_unlock(&o->lock);
    return n;
}

/* batchrt.h, brt_read_fn: never called by two threads at once -- a load
** that is not the blob read ahead waits for the read-ahead first. */
static void test_reads_one_at_a_time(void)
{
    bench b;
    brt_trace_options opt;
    brt_stats st;
    overlap_reader o;
    CHECK(fault_bench(&b), "cannot build the bench");
    fault_options(&opt, NULL);
    memset(&o, 0, sizeof o);
    pthread_mutex_init(&o.lock, NULL);
    o.caller = pthread_self();
    opt.read_fn = overlap_read;
    opt.read_user = &o;
    opt.threads = 2;
    if (trace_equals_direct(&b, &opt, &st, "two threads, a slow reader"))
        EXPECT(o.overlaps == 0 && o.calls > 20, "%d of %ld reads began while another was under way",
               o.overlaps, o.calls);
    pthread_mutex_destroy(&o.lock);
    bench_free(&b);
}

typedef struct write_job {
    const char *path;
    int which;          /* 0 hits, 1 rays, 2 statistics, 3 a scene */
    const brt_mesh *mesh;
    brt_error err;
} write_job;

static brt_result write_one(void *arg)
{
    write_job *job = arg;
    brt_hit hits[64];
    brt_ray rays[64];
    brt_stats stats;
    brt_scene_options opt;
    int i;
    for (i = 0; i < 64; i++) brt_hit_clear(&hits[i]);
    memset(rays, 0, sizeof rays);
    memset(&stats, 0, sizeof stats);
    memset(&opt, 0, sizeof opt);
    opt.point_tris = 50;
    opt.proxy_res = 8;
    switch (job->which) {
    case 0: return brt_hits_write(job->path, hits, 64, &job->err);
    case 1: return brt_rays_write(job->path, rays, 64, &job->err);
    case 2: return brt_stats_write_json(job->path, &stats, &job->err);
    default: return brt_scene_build(job->mesh, &opt, 1, job->path, &job->err);
    }
}

/* The last steps of a write.  A device that is full (/dev/full, through
** a link: ENOSPC on every write) takes the hit, ray and statistics files
** written to it directly, and each reports "No space left on device"; a file-size limit
** below a hit file's or a statistics file's size fails it with EFBIG,
** leaving nothing; and a target that is a directory is refused: the
** files written in place of a special file fail to open it (BRT_EIO), a
** scene build refuses it first (BRT_EARG), each naming the path, the
** directory untouched, no temporary file left.  (The writer does not
** fsync: there is no fsync to fail; a failing rename needs a target that
** turns into a directory between the check and the rename, which no test
** here can arrange.) */
static void test_write_last_steps(void)
{
    static const char *const kind[] = {"hit file", "ray file", "statistics", "scene file"};
    tu_scene soup = {0};
    brt_mesh mesh;
    write_job job;
    uint64_t seed = test_seed() + 73;
    struct stat st;
    int k;
    brt_result r;
    tu_random_soup(&soup, &seed, 200, 0.1f);
    mesh = tu_mesh_view(&soup);
    job.mesh = &mesh;
    /* Through a link in the scratch folder: a writer that wrongly renamed
    ** over its target would replace the link, never the device. */
    unlink(scratch("full-device"));
    for (k = 0; k < 3 && file_exists("/dev/full"); k++) {
        CHECK(symlink("/dev/full", scratch("full-device")) == 0, "cannot link to /dev/full");
        job.which = k;
        job.path = scratch("full-device");
        r = write_one(&job);
        EXPECT(r == BRT_EIO && strstr(job.err.message, "full-device") && strstr(job.err.message, strerror(ENOSPC)),
               "%s to /dev/full: %s, '%s'", kind[k], brt_result_string(r), job.err.message);
        unlink(scratch("full-device"));
    }
    for (k = 0; k < 3; k += 2) {
        job.which = k;
        job.path = scratch("limited.out");
        r = with_file_limit(100, write_one, &job);
        EXPECT(r == BRT_EIO && strstr(job.err.message, strerror(EFBIG)) && !file_exists(job.path) &&
               !tu_temporary_file_left(), "%s under a limit of 100 bytes: %s, '%s'", kind[k],
               brt_result_string(r), job.err.message);
    }
    for (k = 0; k < 4; k++) {
        char path[600];
        snprintf(path, sizeof path, "%s", scratch("a-directory"));
        CHECK(mkdir(path, 0700) == 0, "cannot make %s", path);
        job.which = k;
        job.path = path;
        r = write_one(&job);
        EXPECT(r == (k == 3 ? BRT_EARG : BRT_EIO) && strstr(job.err.message, path),
               "%s onto a directory: %s, '%s'", kind[k],
               brt_result_string(r), job.err.message);
        EXPECT(stat(path, &st) == 0 && S_ISDIR(st.st_mode) && !tu_temporary_file_left(),
               "%s onto a directory: the directory changed or a temporary file is left", kind[k]);
        rmdir(path);
    }
    tu_scene_free(&soup);
}

/* ===================================================================== */
/* Limits                                                                */
/* ===================================================================== */

/* Every combination of a few settings: batched == direct. */
static void sweep_limits(bench *b, const uint32_t *batch, int nbatch, const char *name)
{
    static const uint64_t memory[] = {0, 1, 4096};
    static const uint32_t in_flight[] = {1, 3, 1000};
    brt_trace_options opt;
    int i, m, f, proxy;
    for (i = 0; i < nbatch && !test_failed(); i++) {
        if (!bench_scene(b, batch[i], i % 2 ? 2 : 16, "limits.brs")) return;
        for (m = 0; m < 3; m++)
            for (f = 0; f < 3; f++)
                for (proxy = 0; proxy < 3 && !test_failed(); proxy++) {
                    static const char *const kind[3] = {"off", "on", "exact, all queued"};
                    char what[160];
                    memset(&opt, 0, sizeof opt);
                    opt.memory_limit = memory[m];
                    opt.rays_in_flight = in_flight[f];
                    opt.no_proxy = !proxy;
                    /* the exact proxies of the analysis mode must give the
                    ** direct hits too; queueing every ray makes every
                    ** visit meet the test */
                    opt.exact_proxies = opt.paper_scheduler = proxy == 2;
                    snprintf(what, sizeof what, "%s: batch %u, memory %llu, %u in flight, "
                             "proxies %s", name, batch[i], (unsigned long long)memory[m],
                             in_flight[f], kind[proxy]);
                    trace_equals_direct(b, &opt, NULL, what);
                }
    }
}

/* One triangle: the direct hits are also checked against the one test. */
static void test_single_triangle(void)
{
    static const uint32_t batch[] = {1, 100000};
    bench b;
    size_t i, hits = 0;
    memset(&b, 0, sizeof b);
    /* Separate statements: the order of evaluation of arguments is unspecified. */
    tu_add_vertex(&b.mesh, 0.1f, 0.2f, 0.3f);
    tu_add_vertex(&b.mesh, 0.9f, 0.25f, 0.35f);
    tu_add_vertex(&b.mesh, 0.3f, 0.8f, 0.6f);
    tu_add_triangle(&b.mesh, 0, 1, 2);
    CHECK(bench_rays(&b, 100, test_seed() + 73), "out of memory");
    for (i = 0; i < b.count; i++) {
        brt_hit expected;
        float t, u, v;
        brt_hit_clear(&expected);
        if (brt_intersect_triangle(&b.rays[i], b.mesh.pos, b.mesh.pos + 3, b.mesh.pos + 6, &t,
                                   &u, &v)) {
            expected.t = t; expected.prim = 0; expected.u = u; expected.v = v;
            hits++;
        }
        EXPECT(memcmp(&expected, &b.direct[i], sizeof expected) == 0, "ray %zu: direct t=%a "
               "prim %u u=%a v=%a, the triangle test t=%a prim %u u=%a v=%a", i, b.direct[i].t,
               (unsigned)b.direct[i].prim, b.direct[i].u, b.direct[i].v, expected.t,
               (unsigned)expected.prim, expected.u, expected.v);
    }
    EXPECT(hits > b.count / 10, "only %zu of %zu rays hit the triangle", hits, b.count);
    sweep_limits(&b, batch, 2, "one triangle");
    bench_free(&b);
}

/* 100 copies of one triangle, sharing vertices or not: every hit is the
** lowest prim, 0, at the distance of triangle 0. */
static void test_identical_triangles(void)
{
    static const uint32_t batch[] = {1, 7, 1000};
    bench b;
    uint32_t i, first[3];
    size_t r;
    int c;
    memset(&b, 0, sizeof b);
    first[0] = tu_add_vertex(&b.mesh, -0.5f, -0.4f, 0.1f);
    first[1] = tu_add_vertex(&b.mesh, 0.6f, -0.3f, -0.2f);
    first[2] = tu_add_vertex(&b.mesh, 0.0f, 0.7f, 0.3f);
    for (i = 0; i < 100; i++) {
        uint32_t v[3];
        for (c = 0; c < 3; c++)
            v[c] = i % 2 ? first[c] : tu_add_vertex(&b.mesh, b.mesh.pos[3 * first[c]],
                                                    b.mesh.pos[3 * first[c] + 1],
                                                    b.mesh.pos[3 * first[c] + 2]);
        tu_add_triangle(&b.mesh, v[0], v[1], v[2]);
    }
    CHECK(bench_rays(&b, 30, test_seed() + 74), "out of memory");
    for (r = 0; r < b.count; r++) {
        float t, u, v;
        int hit = brt_intersect_triangle(&b.rays[r], b.mesh.pos, b.mesh.pos + 3, b.mesh.pos + 6,
                                         &t, &u, &v);
        EXPECT(hit ? b.direct[r].prim == 0 && b.direct[r].t == t : b.direct[r].prim == BRT_NO_PRIM,
               "ray %zu: prim %u, expected %s", r, (unsigned)b.direct[r].prim,
               hit ? "0" : "a miss");
    }
    sweep_limits(&b, batch, 3, "identical triangles");
    bench_free(&b);
}

/* A top level whose root names one subtree twice, every checksum repaired
** as a forger would: a walk would meet that subtree twice (and outgrow its
** heap, sized for a tree), so the file is refused. */
#define TOP_NONE 0xFFFFFFFFu   /* an unused child slot of a top-level node */

static void test_top_level_must_be_a_tree(void)
{
    bench b;
    brt_error err;
    brt_scene *scene = NULL;
    size_t size = 0;
    unsigned char *file;
    uint32_t child[4], node = TOP_NONE;
    uint64_t top, st = test_seed() + 76;
    int lane, other = -1, built;
    memset(&b, 0, sizeof b);
    tu_random_soup(&b.mesh, &st, 400, 0.03f);
    built = bench_scene(&b, 10, 16, "tree.brs");   /* 40 batching points: a few nodes */
    bench_free(&b);
    if (!built) return;
    file = tu_slurp(scratch("tree.brs"), &size);
    CHECK(file && size >= 256, "cannot read tree.brs back");
    memcpy(&top, file + 80, sizeof top);            /* the top-level section's offset */
    if (top > size || size - top < 112) {
        free(file);
        CHECK(0, "the top level lies outside the file");
    }
    memcpy(child, file + top + 96, sizeof child);   /* the root's children */
    for (lane = 0; lane < 4; lane++) {
        if (child[lane] < 0x80000000u && node == TOP_NONE) node = child[lane];
        else if (child[lane] != TOP_NONE) other = lane;
    }
    if (node != TOP_NONE && other >= 0) {
        child[other] = node;
        memcpy(file + top + 96, child, sizeof child);
        fuzz_repair_scene_checksums(file, size);
    }
    EXPECT(node != TOP_NONE && other >= 0, "the root has no subtree beside another child");
    if (!test_failed() && spill("shared.brs", file, size)) {
        EXPECT(brt_scene_open(scratch("shared.brs"), &scene, &err) == BRT_EFORMAT,
               "a top level with a shared subtree opened");
        EXPECT(!scene && strstr(err.message, "bad child") != NULL, "message: %s", err.message);
    }
    brt_scene_close(scene);
    free(file);
}

/* A budget one byte below the only batching point: every load is an
** oversized one, the results stay exact; and a trace of no rays. */
static void test_budget_below_one_batching_point(void)
{
    bench b;
    brt_trace_options opt;
    brt_stats stats;
    brt_hit none;
    brt_error err;
    uint64_t st = test_seed() + 75;
    memset(&b, 0, sizeof b);
    tu_random_soup(&b.mesh, &st, 2000, 0.03f);
    memset(&opt, 0, sizeof opt);
    opt.no_proxy = 1;
    if (bench_rays(&b, 100, st) && bench_scene(&b, 100000, 16, "one_point.brs")
        && trace_equals_direct(&b, &opt, &stats, "no limit")) {
        EXPECT(stats.batching_points == 1 && stats.geometry_bytes > 1, "%llu batching points",
               (unsigned long long)stats.batching_points);
        opt.memory_limit = stats.geometry_bytes - 1;
        opt.rays_in_flight = 1;
        if (trace_equals_direct(&b, &opt, &stats, "a budget below the batching point"))
            EXPECT(stats.batch_loads > 0 && stats.oversized_loads == stats.batch_loads,
                   "%llu loads, %llu oversized", (unsigned long long)stats.batch_loads,
                   (unsigned long long)stats.oversized_loads);
        EXPECT(brt_scene_trace(b.scene, &opt, b.rays, 0, &none, &stats, &err) == BRT_OK
               && stats.rays == 0, "a trace of no rays: %s", err.message);
    }
    bench_free(&b);
}

/* ===================================================================== */
/* Forged scene files: one per validator                                */
/* ===================================================================== */
/*
** The fuzz target's fixed scene (25 triangles in 4 batching points) with
** one cross-reference broken and every checksum repaired, as a forger (and
** the scene fuzz target) would; then opened and, when it opens, traced
** with exact proxies, which load every blob.  Each must be refused with
** BRT_EFORMAT and a message naming the file and the part.  The unbroken
** file goes the same way and must trace, so a refusal is the forgery's.
** Offsets: scene.c's scene file (header fields at fixed offsets, 80-byte
** batch entries, 112-byte top-level nodes) and bvh.c's blob (64-byte
** header, 128-byte nodes, 36 bytes a triangle, then 4-byte numbers).
*/
typedef struct forged {
    unsigned char *file;
    size_t size;
} forged;

static uint64_t forged_u64(const forged *f, uint64_t at)
{
    uint64_t v = 0;
    if (at <= f->size && f->size - at >= 8) memcpy(&v, f->file + at, 8);
    return v;
}

static uint32_t forged_u32(const forged *f, uint64_t at)
{
    uint32_t v = 0;
    if (at <= f->size && f->size - at >= 4) memcpy(&v, f->file + at, 4);
    return v;
}

static float forged_f32(const forged *f, uint64_t at)
{
    uint32_t bits = forged_u32(f, at);
    float v;
    memcpy(&v, &bits, 4);
    return v;
}

static void forge_bytes(forged *f, uint64_t at, const void *v, size_t n)
{
    if (at <= f->size && f->size - at >= n) memcpy(f->file + at, v, n);
}

static void forge_u32(forged *f, uint64_t at, uint32_t v) { forge_bytes(f, at, &v, 4); }
static void forge_u64(forged *f, uint64_t at, uint64_t v) { forge_bytes(f, at, &v, 8); }
static void forge_f32(forged *f, uint64_t at, float v) { forge_bytes(f, at, &v, 4); }

/* Batch entry i, the root of the top level, blob i's parts. */
static uint64_t entry_at(const forged *f, uint32_t i) { return forged_u64(f, 56) + 80u * i; }
static uint64_t top_root_at(const forged *f) { return forged_u64(f, 80); }
static uint64_t blob_at(const forged *f, uint32_t i) { return forged_u64(f, entry_at(f, i) + 24); }
/* A blob (bvh.c, scene format 2): 64-byte header {magic, nodes, vertices,
** triangles}, 64-byte nodes, 12-byte vertices, u32 prims, u16 corners. */
static uint64_t blob_verts_at(const forged *f, uint32_t i)
{
    return blob_at(f, i) + 64 + 64 * (uint64_t)forged_u32(f, blob_at(f, i) + 4);
}
static uint64_t blob_prims_at(const forged *f, uint32_t i)
{
    return blob_verts_at(f, i) + 12 * (uint64_t)forged_u32(f, blob_at(f, i) + 8);
}

/* header: no batching points (and a table to match) */
static void forge_header_points(forged *f)
{
    forge_u32(f, 32, 0);
    forge_u64(f, 64, 0);
}
/* header: 5 top-level nodes for 4 points (and a section to match) */
static void forge_header_nodes(forged *f)
{
    forge_u32(f, 40, 5);
    forge_u64(f, 88, 5 * 112);
}
/* header: the point table, or the top level, one record longer than its count */
static void forge_header_table(forged *f) { forge_u64(f, 64, forged_u64(f, 64) + 80); }
static void forge_header_top(forged *f) { forge_u64(f, 88, forged_u64(f, 88) + 112); }
static void forge_batch_box(forged *f) { forge_f32(f, entry_at(f, 1), NAN); }
static void forge_blob_extent(forged *f) { forge_u64(f, entry_at(f, 1) + 24, f->size); }
static void forge_proxy_root(forged *f) { forge_u32(f, entry_at(f, 1) + 52, 0x7FFFFFF0u); }
/* the header's proxy resolution 8, the proxies' (valid) 4 */
static void forge_proxy_res(forged *f) { forge_u32(f, 28, 8); }
/* The inner proxy's root (README, "Inner proxies"), past the pool. */
static void forge_inner_root(forged *f) { forge_u32(f, entry_at(f, 1) + 76, 0x7FFFFFF0u); }
static void forge_triangle_sum(forged *f) { forge_u32(f, 36, forged_u32(f, 36) + 1); }
static void forge_byte_sum(forged *f) { forge_u64(f, 48, forged_u64(f, 48) + 1); }
static void forge_top_box(forged *f) { forge_f32(f, top_root_at(f), -INFINITY); }
/* lane 0's max x down to its min x: ordered, but narrower than its point */
static void forge_top_nesting(forged *f)
{
    forge_f32(f, top_root_at(f) + 48, forged_f32(f, top_root_at(f)));
}
static void forge_top_leaf(forged *f) { forge_u32(f, top_root_at(f) + 96, 0x80000000u | 100u); }
static void forge_top_missing(forged *f) { forge_u32(f, top_root_at(f) + 96, 0xFFFFFFFFu); }
static void forge_prim_number(forged *f) { forge_u32(f, blob_prims_at(f, 1), 25); }
static void forge_prim_no_prim(forged *f) { forge_u32(f, blob_prims_at(f, 1), BRT_NO_PRIM); }
static void forge_blob_box(forged *f) { forge_f32(f, blob_at(f, 1) + 64, NAN); }
static void forge_blob_triangle(forged *f) { forge_f32(f, blob_verts_at(f, 1), INFINITY); }
/* one triangle moved between two table entries: the sums still agree */
static void forge_blob_count(forged *f)
{
    forge_u32(f, entry_at(f, 1) + 48, forged_u32(f, entry_at(f, 1) + 48) + 1);
    forge_u32(f, entry_at(f, 2) + 48, forged_u32(f, entry_at(f, 2) + 48) - 1);
}

/* Every axis (issue 32 class 4): a point's box inverted in y, infinite
** in z; a root lane's box infinite in y and z (holding its point, so that
** only the box check refuses it); a root lane narrower than its point in
** y and z.  Root lanes: f32 lo[axis][lane] at 4 (4 axis + lane), hi 48 on. */
static void forge_batch_box_y(forged *f)
{
    forge_f32(f, entry_at(f, 2) + 4, forged_f32(f, entry_at(f, 2) + 16) + 1);
}
static void forge_batch_box_z(forged *f) { forge_f32(f, entry_at(f, 3) + 20, INFINITY); }
static void forge_top_box_y(forged *f) { forge_f32(f, top_root_at(f) + 4 * (4 + 1), -INFINITY); }
static void forge_top_box_z(forged *f) { forge_f32(f, top_root_at(f) + 48 + 4 * (8 + 2), INFINITY); }
static void forge_top_nesting_y(forged *f)
{
    forge_f32(f, top_root_at(f) + 48 + 4 * (4 + 1), forged_f32(f, top_root_at(f) + 4 * (4 + 1)));
}
static void forge_top_nesting_z(forged *f)
{
    forge_f32(f, top_root_at(f) + 4 * (8 + 3), forged_f32(f, top_root_at(f) + 48 + 4 * (8 + 3)));
}
/* The header: the other byte order's mark; version 4 without prototypes. */
static void forge_endian(forged *f) { forge_u32(f, 12, 0x04030201u); }
static void forge_v4_empty(forged *f) { forge_u32(f, 8, 4); }
/* Sections (header 56 + 24 s: offset, size): the proxy pool's offset past
** the end, its size wrapping offset + size around 2^64, its size one byte
** past the end; the point table overlapping the end; the top level's
** offset near 2^64.  (The table sizes themselves are check_header's.) */
static void forge_pool_offset(forged *f) { forge_u64(f, 104, f->size + 4096); }
static void forge_pool_wrap(forged *f) { forge_u64(f, 112, UINT64_MAX - forged_u64(f, 104) + 4097); }
static void forge_pool_past(forged *f) { forge_u64(f, 112, f->size - forged_u64(f, 104) + 1); }
static void forge_table_end(forged *f) { forge_u64(f, 56, f->size - 8); }
static void forge_top_offset(forged *f) { forge_u64(f, 80, UINT64_MAX - 8); }
/* Blobs apart: point 1's blob made point 0's (counts and sums kept
** agreeing), or put on the header's page; point 0's a page longer. */
static void forge_blob_header(forged *f) { forge_u64(f, entry_at(f, 1) + 24, 0); }
/* point 0's blob a page longer: into point 1's, which follows it */
static void forge_blob_longer(forged *f)
{
    forge_u64(f, entry_at(f, 0) + 32, forged_u64(f, entry_at(f, 0) + 32) + 4096);
    forge_u64(f, 48, forged_u64(f, 48) + 4096);
}
static void forge_blob_overlap(forged *f)
{
    const uint32_t moved = forged_u32(f, entry_at(f, 1) + 48), kept = forged_u32(f, entry_at(f, 0) + 48);
    forge_u64(f, 48, forged_u64(f, 48) - forged_u64(f, entry_at(f, 1) + 32) + forged_u64(f, entry_at(f, 0) + 32));
    forge_u32(f, 36, forged_u32(f, 36) - moved + kept);
    forge_u64(f, entry_at(f, 1) + 24, forged_u64(f, entry_at(f, 0) + 24));
    forge_u64(f, entry_at(f, 1) + 32, forged_u64(f, entry_at(f, 0) + 32));
    forge_u32(f, entry_at(f, 1) + 48, kept);
}

typedef struct forgery {
    const char *name;           /* also the file's name */
    void (*forge)(forged *f);
    const char *part;           /* what the message must name */
} forgery;

static const forgery forgeries[] = {
    {"header_points.brs", forge_header_points, "header: no batching points"},
    {"header_nodes.brs", forge_header_nodes, "header: 5 top-level nodes for 4 batching points"},
    {"header_table.brs", forge_header_table, "header: point table has the wrong size"},
    {"header_top.brs", forge_header_top, "header: top-level section has the wrong size"},
    {"batch_box.brs", forge_batch_box, "batching point 1: box not finite"},
    {"blob_extent.brs", forge_blob_extent, "batching point 1: blob outside the file"},
    {"proxy_root.brs", forge_proxy_root, "batching point 1: invalid proxy"},
    {"proxy_res.brs", forge_proxy_res, "batching point 0: invalid proxy"},
    {"inner_root.brs", forge_inner_root, "batching point 1: invalid inner proxy"},
    {"triangle_sum.brs", forge_triangle_sum, "point table: batching points hold 25 triangles"},
    {"byte_sum.brs", forge_byte_sum, "point table: blobs hold"},
    {"top_box.brs", forge_top_box, "top-level node 0: box not finite"},
    {"top_nesting.brs", forge_top_nesting, "top-level node 0: box does not hold batching point"},
    {"top_leaf.brs", forge_top_leaf, "top-level node 0: bad leaf"},
    {"top_missing.brs", forge_top_missing, "not in the top level"},
    {"prim_number.brs", forge_prim_number, "batching point 1: bvh blob: triangle 0: number 25"},
    {"prim_no_prim.brs", forge_prim_no_prim, "batching point 1: bvh blob: triangle 0: number"},
    {"blob_box.brs", forge_blob_box, "batching point 1: bvh blob: node 0 slot 0: box"},
    {"blob_triangle.brs", forge_blob_triangle, "batching point 1: bvh blob: vertex 0: coordinate"},
    {"blob_count.brs", forge_blob_count, "batching point 1: blob holds"},
    {"batch_box_y.brs", forge_batch_box_y, "batching point 2: box not finite or inverted"},
    {"batch_box_z.brs", forge_batch_box_z, "batching point 3: box not finite or inverted"},
    {"top_box_y.brs", forge_top_box_y, "top-level node 0: box not finite or inverted"},
    {"top_box_z.brs", forge_top_box_z, "top-level node 0: box not finite or inverted"},
    {"top_nesting_y.brs", forge_top_nesting_y, "top-level node 0: box does not hold batching point"},
    {"top_nesting_z.brs", forge_top_nesting_z, "top-level node 0: box does not hold batching point"},
    {"endian.brs", forge_endian, "of the other byte order"},
    {"v4_empty.brs", forge_v4_empty, "header: version 4 without prototypes"},
    {"pool_offset.brs", forge_pool_offset, "proxy pool lies outside the file"},
    {"pool_wrap.brs", forge_pool_wrap, "proxy pool lies outside the file"},
    {"pool_past.brs", forge_pool_past, "proxy pool lies outside the file"},
    {"table_end.brs", forge_table_end, "point table lies outside the file"},
    {"top_offset.brs", forge_top_offset, "top-level BVH lies outside the file"},
    {"blob_overlap.brs", forge_blob_overlap, "blob table: blobs overlap at byte 4096"},
    {"blob_header.brs", forge_blob_header, "blob table: blobs overlap at byte 0"},
    {"blob_longer.brs", forge_blob_longer, "blob table: blobs overlap at byte"},
};

/* Writes base forged by fn (none: unchanged) with repaired checksums as
** name, opens it, traces one ray loading every blob; the result, and the
** message in err. */
static void repair_plain(forged *f) { fuzz_repair_scene_checksums(f->file, f->size); }

/* base forged by fn (none: unchanged), its checksums repaired by repair,
** written as name and opened. */
static brt_result forged_open(const forged *base, const char *name, void (*fn)(forged *),
                              void (*repair)(forged *), brt_scene **scene, brt_error *err)
{
    forged f;
    brt_result r = BRT_ENOMEM;
    *scene = NULL;
    f.size = base->size;
    f.file = malloc(f.size);
    if (!f.file) return r;
    memcpy(f.file, base->file, f.size);
    if (fn) fn(&f);
    repair(&f);
    err->message[0] = 0;
    r = spill(name, f.file, f.size) ? brt_scene_open(scratch(name), scene, err) : BRT_EIO;
    free(f.file);
    return r;
}

static brt_result open_forged(const forged *base, const char *name, void (*fn)(forged *),
                              brt_error *err)
{
    brt_scene *scene;
    brt_trace_options opt;
    brt_ray ray = {{0.1f, 0.1f, 3.0f}, {0.0f, 0.0f, -1.0f}, 0.0f, INFINITY};
    brt_hit hit;
    brt_result r = forged_open(base, name, fn, repair_plain, &scene, err);
    if (r != BRT_OK) return r;
    memset(&opt, 0, sizeof opt);
    opt.exact_proxies = 1;   /* loads every blob */
    r = brt_scene_trace(scene, &opt, &ray, 1, &hit, NULL, err);
    brt_scene_close(scene);
    return r;
}

static void test_forged_scenes(void)
{
    forged base;
    brt_error err;
    size_t i;
    CHECK(fuzz_fixed_scene_build(scratch("forge_base.brs"), &err) == BRT_OK, "%s", err.message);
    base.file = tu_slurp(scratch("forge_base.brs"), &base.size);
    CHECK(base.file && base.size >= 256 && forged_u32(&base, 32) == 4 && forged_u32(&base, 36) == 25
          && forged_u32(&base, 40) == 1, "the fixed scene is not 25 triangles, 4 points, 1 node");
    EXPECT(open_forged(&base, "unforged.brs", NULL, &err) == BRT_OK, "unforged: %s", err.message);
    for (i = 0; i < sizeof forgeries / sizeof *forgeries; i++) {
        const forgery *g = &forgeries[i];
        brt_result r = open_forged(&base, g->name, g->forge, &err);
        EXPECT(r == BRT_EFORMAT, "%s: %s, expected a format error", g->name, brt_result_string(r));
        EXPECT(strstr(err.message, g->name) && strstr(err.message, g->part),
               "%s: message '%s' lacks '%s'", g->name, err.message, g->part);
    }
    free(base.file);
}

/* The fixed mesh in 25 batching points (a top level of several nodes): a
** root lane over a node narrowed to zero width in x, still ordered and
** finite, no longer holds that node's boxes. */
static void forge_node_nesting(forged *f)
{
    uint64_t root = top_root_at(f);
    int lane;
    for (lane = 0; lane < 4; lane++)
        if (forged_u32(f, root + 96 + 4 * (uint64_t)lane) < 0x80000000u) {
            forge_f32(f, root + 48 + 4 * (uint64_t)lane, forged_f32(f, root + 4 * (uint64_t)lane));
            return;
        }
}

static void test_forged_node_nesting(void)
{
    brt_scene_options opt;
    brt_mesh mesh;
    forged base;
    brt_error err;
    brt_result r;
    fuzz_fixed_mesh(&mesh);
    memset(&opt, 0, sizeof opt);
    opt.point_tris = 1;
    opt.proxy_res = 4;
    CHECK(brt_scene_build(&mesh, &opt, 0, scratch("nodes_base.brs"), &err) == BRT_OK, "%s", err.message);
    base.file = tu_slurp(scratch("nodes_base.brs"), &base.size);
    CHECK(base.file && base.size >= 256 && forged_u32(&base, 40) > 1, "no top level of several nodes");
    EXPECT(open_forged(&base, "nodes.brs", NULL, &err) == BRT_OK, "unforged: %s", err.message);
    r = open_forged(&base, "node_nesting.brs", forge_node_nesting, &err);
    EXPECT(r == BRT_EFORMAT && strstr(err.message, "node_nesting.brs: top-level node 0: box does "
                                      "not hold node"), "forged top-level nesting: %s: %s", brt_result_string(r),
           err.message);
    free(base.file);
}

/* Blob 1's first triangle renumbered as blob 0's first: every validator
** of scene open passes (numbers below the count, counts and sums agree),
** and only the partition checker sees a triangle in two batching points.
** (Its "in no batching point" check cannot fire alone: n numbers below n
** with one missing repeat one, pigeonhole, and the repeat is found first.) */
static void forge_prim_twice(forged *f)
{
    forge_u32(f, blob_prims_at(f, 1), forged_u32(f, blob_prims_at(f, 0)));
}

static void test_forged_partition(void)
{
    forged base;
    brt_error err;
    brt_scene *scene = NULL;
    brt_result r;
    CHECK(fuzz_fixed_scene_build(scratch("twice_base.brs"), &err) == BRT_OK, "%s", err.message);
    base.file = tu_slurp(scratch("twice_base.brs"), &base.size);
    CHECK(base.file && base.size >= 256 && forged_u32(&base, 32) == 4, "the fixed scene has not 4 points");
    EXPECT(open_forged(&base, "twice.brs", forge_prim_twice, &err) == BRT_OK,
           "the forgery should pass scene open: %s", err.message);
    CHECK(brt_scene_open(scratch("twice.brs"), &scene, &err) == BRT_OK, "%s", err.message);
    r = brt_scene_check_partition(scene, 25, &err);
    EXPECT(r == BRT_ECHECK && strstr(err.message, "twice.brs: triangle ") &&
           strstr(err.message, "is in two batching points (again in 1)"), "%s: %s",
           brt_result_string(r), err.message);
    brt_scene_close(scene);
    free(base.file);
}

/* An instanced scene file (version 4, README "The scene file"):
** tu_instanced_squares, a world triangle and four instances of a square. */
static int instanced_base(forged *base)
{
    tu_instanced s;
    brt_scene_source source;
    brt_scene_options opt;
    brt_error err;
    int ok;
    tu_instanced_squares(&s);
    tu_instanced_source(&s, &source);
    memset(&opt, 0, sizeof opt);
    opt.proxy_res = 8;
    ok = brt_scene_build_source(&source, &opt, 1, scratch("inst_base.brs"), &err) == BRT_OK;
    if (!ok) test_fail_at(__FILE__, __LINE__, "%s", err.message);
    tu_instanced_free(&s);
    base->file = ok ? tu_slurp(scratch("inst_base.brs"), &base->size) : NULL;
    return base->file && base->size >= 256 && forged_u32(base, 8) == 4 && forged_u32(base, 44) == 1;
}

/* Its parts: batch entries of 104 bytes (instances at 80, condition 84),
** the prototype table (section at 128: 56-byte entries, offset 0, box 28). */
static uint64_t entry4_at(const forged *f, uint32_t i) { return forged_u64(f, 56) + 104u * i; }
static uint64_t proto_at(const forged *f) { return forged_u64(f, 128); }
static uint64_t instance_point_at(const forged *f)
{
    uint32_t i;
    for (i = 0; i < forged_u32(f, 32); i++)
        if (forged_u32(f, entry4_at(f, i) + 80)) return entry4_at(f, i);
    return 0;
}

/* The checksums of a version-4 file after a forgery: every blob's, the
** four sections', the header's (each only where it lies in the file). */
static void repair_instanced(forged *f)
{
    uint64_t at[16];
    uint32_t n = 0, i;
    for (i = 0; i < forged_u32(f, 32) && n < 8; i++) at[n++] = entry4_at(f, i) + 24;
    at[n++] = proto_at(f);
    for (i = 0; i < 3; i++) at[n++] = 56 + 24 * (uint64_t)i;
    at[n++] = 128;
    for (i = 0; i < n; i++) {
        const uint64_t off = forged_u64(f, at[i]), size = forged_u64(f, at[i] + 8);
        if (off <= f->size && size <= f->size - off) forge_u64(f, at[i] + 16, brt_checksum64(f->file + off, size));
    }
    forge_u64(f, 248, brt_checksum64(f->file, 248));
}

static void forge_header_condition(forged *f) { forge_f32(f, 156, -1.0f); }
static void forge_header_reach(forged *f) { forge_f32(f, 160, INFINITY); }
static void forge_header_centre(forged *f) { forge_f32(f, 184, NAN); }
static void forge_proto_table(forged *f) { forge_u64(f, 136, forged_u64(f, 136) + 56); }
static void forge_proto_blob(forged *f) { forge_u64(f, proto_at(f), (f->size + 4095) / 4096 * 4096); }
static void forge_proto_box(forged *f) { forge_f32(f, proto_at(f) + 28 + 4, NAN); }
static void forge_point_instances(forged *f)
{
    forge_u32(f, instance_point_at(f) + 80, forged_u32(f, 152) + 1);
}
static void forge_point_condition(forged *f) { forge_f32(f, instance_point_at(f) + 84, 2048.0f); }
static void forge_point_reach(forged *f) { forge_f32(f, instance_point_at(f) + 96, -1.0f); }

/* One forged instanced file per validator of the version-4 parts. */
static void test_forged_instanced_scenes(void)
{
    static const forgery forged_v4[] = {
        {"inst_condition.brs", forge_header_condition, "header: margin out of range"},
        {"inst_reach.brs", forge_header_reach, "header: margin out of range"},
        {"inst_centre.brs", forge_header_centre, "header: margin out of range"},
        {"inst_proto_table.brs", forge_proto_table, "header: prototype table has the wrong size"},
        {"inst_proto_blob.brs", forge_proto_blob, "prototype 0: blob outside the file"},
        {"inst_proto_box.brs", forge_proto_box, "prototype 0: box not finite or inverted"},
        {"inst_point_count.brs", forge_point_instances, "instances or margin out of range"},
        {"inst_point_condition.brs", forge_point_condition, "instances or margin out of range"},
        {"inst_point_reach.brs", forge_point_reach, "instances or margin out of range"},
    };
    forged base;
    size_t i;
    CHECK(instanced_base(&base), "no instanced scene file of version 4 with one prototype");
    CHECK(instance_point_at(&base) != 0, "no point of instances in the file");
    for (i = 0; i < sizeof forged_v4 / sizeof *forged_v4 + 1; i++) {
        const forgery *g = i ? &forged_v4[i - 1] : NULL;
        brt_scene *scene;
        brt_error err;
        brt_result r = forged_open(&base, g ? g->name : "inst_unforged.brs", g ? g->forge : NULL,
                                   repair_instanced, &scene, &err);
        brt_scene_close(scene);
        if (!g) {
            EXPECT(r == BRT_OK, "unforged, checksums repaired: %s", err.message);
            continue;
        }
        EXPECT(r == BRT_EFORMAT && strstr(err.message, g->name) && strstr(err.message, g->part),
               "%s: %s, '%s' (expected '%s')", g->name, brt_result_string(r), err.message, g->part);
    }
    free(base.file);
}

/* The validators refuse forgeries, not extremes: a scene built from
** triangles at +-FLT_MAX (padded BVH boxes round out to infinity there,
** and a proxy grid's far corner overflows a float) opens, loads every blob
** and traces, with the hit brute force gives. */
static void test_extreme_scene_opens(void)
{
    static float pos[] = {-FLT_MAX, -FLT_MAX, 0, FLT_MAX, -FLT_MAX, 0, -FLT_MAX, FLT_MAX, 0,
                          0, 0, FLT_MAX, 1, 0, FLT_MAX, 0, 1, -FLT_MAX};
    static uint32_t idx[] = {0, 1, 2, 3, 4, 5};
    brt_mesh mesh = {pos, idx, 6, 2};
    brt_scene_options sopt;
    brt_trace_options opt;
    brt_scene *scene = NULL;
    brt_ray ray = {{-1e30f, -1e30f, 1.0f}, {0.0f, 0.0f, -1.0f}, 0.0f, INFINITY};
    brt_hit hit;
    brt_error err;
    float t, u, v;
    memset(&sopt, 0, sizeof sopt);
    sopt.point_tris = 1;   /* two batching points */
    CHECK(brt_scene_build(&mesh, &sopt, 0, scratch("extreme.brs"), &err) == BRT_OK, "%s", err.message);
    CHECK(brt_scene_open(scratch("extreme.brs"), &scene, &err) == BRT_OK, "%s", err.message);
    memset(&opt, 0, sizeof opt);
    opt.exact_proxies = 1;   /* loads every blob */
    EXPECT(brt_scene_trace(scene, &opt, &ray, 1, &hit, NULL, &err) == BRT_OK, "%s", err.message);
    brt_scene_close(scene);
    CHECK(brt_intersect_triangle(&ray, pos, pos + 3, pos + 6, &t, &u, &v), "the ray misses");
    EXPECT(hit.prim == 0 && hit.t == t, "hit prim %u at %g, brute force 0 at %g",
           (unsigned)hit.prim, (double)hit.t, (double)t);
}

void suite_hardening(void)
{
    test_run("hardening: fuzz corpus replays cleanly", test_corpus_replay);
    test_run("hardening: scene fuzz seed opens and repairs to itself", test_scene_seed);
    test_run("hardening: bad input to the programs, exact errors, no files", test_bad_runs);
    test_run("hardening: an empty ray file gives an empty hit file", test_empty_ray_file);
    test_run("hardening: EIO and end of file at every read", test_read_fault_every_call);
    test_run("hardening: short reads of every size, EINTR", test_short_reads_every_size);
    test_run("hardening: file-size limit, no partial scene or ray file", test_write_faults);
    test_run("hardening: programs on a full disk leave nothing", test_full_disk_programs);
    test_run("hardening: a failed read-ahead is dropped and read again", test_read_ahead_faults);
    test_run("hardening: the reader is never called by two threads at once", test_reads_one_at_a_time);
    test_run("hardening: a full device, a size limit, a directory as the target", test_write_last_steps);
    test_run("hardening: one triangle, every limit", test_single_triangle);
    test_run("hardening: a 1x1 render, direct == batched at its limits", test_one_pixel_render);
    test_run("hardening: identical triangles, every limit", test_identical_triangles);
    test_run("hardening: a top level that is not a tree is refused", test_top_level_must_be_a_tree);
    test_run("hardening: budget below one batching point, no rays",
             test_budget_below_one_batching_point);
    test_run("hardening: forged scene files, one per validator, are refused", test_forged_scenes);
    test_run("hardening: forged scene file, a top-level box not holding its node",
             test_forged_node_nesting);
    test_run("hardening: forged scene file, a triangle in two batching points (partition checker)",
             test_forged_partition);
    test_run("hardening: a scene at +-FLT_MAX passes the validators", test_extreme_scene_opens);
    test_run("hardening: forged instanced scene files, one per validator", test_forged_instanced_scenes);
}
