/*
** tests/test_oom.c -- running out of memory, at every allocation (the
** README's "Bad input" contract, for the input a machine gives: memory).
**
** The shim tests/oom/failalloc.c, preloaded into one program run, fails
** the n-th allocation of the process.  The sweep runs `trace` on a small
** pbrt-v4 scene (an Include, an object and its instances, a loopsubdiv
** shape, a PLY mesh) for n = 1, 2, ... until a run makes fewer than n
** allocations.  Every run must either
**   - end with status 1 and one line on stderr that says it ran out of
**     memory ("out of memory", or libc's strerror(ENOMEM) where a libc
**     call reported it), with no hit file, scene file or temporary file
**     left; or
**   - absorb the failure and write the same hit bytes as a run without it.
** Never a crash, a wrong message or a half-written output.  The sweeps
** run with one thread, so that the n-th allocation is the same one in
** every run.  They SKIP under sanitizers and valgrind (which replace
** malloc themselves) and where the shim is inactive (not glibc).
*/
#include "test.h"
#include "util.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#define MAX_ALLOCATIONS 100000   /* far more than any run here makes */

/* The scene: every kind of pbrt input that allocates on its own path. */
static void put_scene(void)
{
    static const char ply[] =
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 -1\n1 0 -1\n1 1 -1\n0 1 -1\n3 0 1 2\n3 0 2 3\n";
    tu_put("oom-part.pbrt", "Shape \"trianglemesh\" \"point3 P\" [-1 -1 0  1 -1 0  0 1 0] \"integer indices\" [0 1 2]\n");
    tu_put("oom-quad.ply", ply);
    tu_put("oom.pbrt",
           "LookAt 0 0 5  0 0 0  0 1 0\nCamera \"perspective\" \"float fov\" 40\n"
           "Film \"rgb\" \"integer xresolution\" 8 \"integer yresolution\" 8\n"
           "WorldBegin\n"
           "Include \"oom-part.pbrt\"\n"
           "ObjectBegin \"leaf\"\n"
           "  Shape \"trianglemesh\" \"point3 P\" [0 0 0  0.3 0 0  0 0.3 0] \"integer indices\" [0 1 2]\n"
           "ObjectEnd\n"
           "AttributeBegin\n  Translate 0.5 0.5 0.2\n  ObjectInstance \"leaf\"\nAttributeEnd\n"
           "AttributeBegin\n  Translate -0.5 0.5 0.2\n  ObjectInstance \"leaf\"\nAttributeEnd\n"
           "AttributeBegin\n  Translate 0 -0.6 0.1\n"
           "  Shape \"loopsubdiv\" \"integer levels\" 1 \"point3 P\" [0 0 0  0.5 0 0  0 0.5 0  0 0 0.5]\n"
           "    \"integer indices\" [0 1 2  0 2 3  0 3 1  1 3 2]\n"
           "AttributeEnd\n"
           "Shape \"plymesh\" \"string filename\" \"oom-quad.ply\"\n");
}

/* One run of OPTIONS (a program and its arguments) with the n-th
** allocation failed; OUTPUT is its main output, "oom.json" its
** statistics.  Returns 0 when it made fewer than n allocations, else 1
** (and records any failure of the contract above). */
static int one_failure(const char *shim, long n, const char *options, const char *output, const char *reference)
{
    char head[3000];
    int status, failed_one;
    char *err;
    unlink(tu_scratch("oom.log"));
    unlink(tu_scratch(output));
    unlink(tu_scratch("oom.json"));
    unlink(tu_scratch("oom.brs"));
    snprintf(head, sizeof head, "LD_PRELOAD='%s' BRT_FAIL_ALLOC=%ld BRT_FAIL_ALLOC_LOG='%s' %s/", shim, n,
             tu_scratch("oom.log"), getenv("BRT_BUILD") ? getenv("BRT_BUILD") : "build");
    status = tu_shell(head, options, "");
    failed_one = tu_file_exists(tu_scratch("oom.log"));
    err = tu_last_stderr();
    if (status == 0) {
        EXPECT(tu_same_file_bytes(tu_scratch(output), reference) && tu_file_exists(tu_scratch("oom.json")),
               "allocation %ld failed and was absorbed, but %s differs from a run without it, or no statistics",
               n, output);
    } else {
        const char *line_end = err ? strchr(err, '\n') : NULL;
        EXPECT(status == 1, "allocation %ld failed: exit status %d, expected 1; stderr: %s", n, status,
               err ? err : "(none)");
        EXPECT(err && line_end && line_end[1] == 0 &&
                   (strstr(err, "out of memory") || strstr(err, "Cannot allocate memory")),
               "allocation %ld failed: stderr is not one line saying out of memory:\n%s", n, err ? err : "(none)");
        EXPECT(!tu_file_exists(tu_scratch(output)) && !tu_file_exists(tu_scratch("oom.json")),
               "allocation %ld failed: %s or the statistics were left behind", n, output);
        /* a scene file is a cache, written whole or not at all: one the
        ** build finished before the failure stays, and must be the one a
        ** run without the failure builds */
        EXPECT(!tu_file_exists(tu_scratch("oom.brs")) ||
                   tu_same_file_bytes(tu_scratch("oom.brs"), tu_scratch("oom-reference.brs")),
               "allocation %ld failed: a scene file unlike the one built without it was left", n);
        EXPECT(!tu_temporary_file_left(), "allocation %ld failed: a temporary file was left behind", n);
    }
    free(err);
    return failed_one;
}

/* The sweep of one program run, OPTIONS, whose main output is OUTPUT. */
static void sweep(const char *options, const char *output)
{
    char shim[2048], reference[1024], cwd[1024] = "";
    const char *build = getenv("BRT_BUILD") ? getenv("BRT_BUILD") : "build";
    long n;
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
    test_skip("under a sanitizer, which replaces malloc itself");
    return;
#endif
    if (getenv("LD_PRELOAD") && strstr(getenv("LD_PRELOAD"), "vgpreload")) {
        test_skip("under valgrind, which replaces malloc itself");
        return;
    }
    /* absolute: the programs run in the same folder, but say so anyway */
    CHECK(build[0] == '/' || getcwd(cwd, sizeof cwd), "getcwd failed");
    snprintf(shim, sizeof shim, "%s%s%s/tests/failalloc.so", build[0] == '/' ? "" : cwd,
             build[0] == '/' ? "" : "/", build);
    CHECK(tu_file_exists(shim), "%s is missing (make test builds it)", shim);
    put_scene();
    CHECK(tu_run("raygen @/oom.pbrt @/oom.rays --kind camera") == 0, "raygen: %s", tu_last_stderr());
    CHECK(tu_run("%s", options) == 0, "%s without a failure: %s", options, tu_last_stderr());
    snprintf(reference, sizeof reference, "%s", tu_scratch("oom-reference.out"));
    CHECK(rename(tu_scratch(output), reference) == 0, "no %s written", output);
    if (tu_file_exists(tu_scratch("oom.brs"))) rename(tu_scratch("oom.brs"), tu_scratch("oom-reference.brs"));
    for (n = 1; n <= MAX_ALLOCATIONS && !test_failed(); n++) {
        if (!one_failure(shim, n, options, output, reference)) break;
    }
    if (n == 1) test_skip("the allocation shim is inactive here (glibc only)");
    EXPECT(n > 1 && n <= MAX_ALLOCATIONS, "the sweep ended at allocation %ld", n);
}

static void test_direct(void)
{
    sweep("trace @/oom.pbrt @/oom.rays @/oom.hits --direct --threads 1 --stats @/oom.json", "oom.hits");
}

static void test_batched(void)
{
    sweep("trace @/oom.pbrt @/oom.rays @/oom.hits --batched --point-tris 2 --proxy-res 8 --scene @/oom.brs "
          "--threads 1 --stats @/oom.json", "oom.hits");
}

static void test_render(void)
{
    sweep("render @/oom.pbrt --spp 1 --threads 1 --point-tris 2 --proxy-res 8 --scene @/oom.brs --out @/oom.png "
          "--stats @/oom.json", "oom.png");
}

void suite_oom(void)
{
    test_run("oom: every allocation of trace --direct on a pbrt scene fails cleanly", test_direct);
    test_run("oom: every allocation of trace --batched on a pbrt scene fails cleanly", test_batched);
    test_run("oom: every allocation of render on a pbrt scene fails cleanly", test_render);
}
