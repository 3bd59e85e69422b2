/*
** tests/test_faults.c -- a read fault on every read the library makes of
** its own files (issue 32, class 6): a scene file's header, tables and
** prototype table at open, and a build's spill and instance files.  The
** fault is injected at the n-th read (brt_test_read_fault), for every n
** until the operation needs no more reads: each fault must end it with
** BRT_EIO and a message naming the file, and a failed build must leave
** neither the scene file nor a temporary file.  (Blob loads and read-ahead
** take faults through brt_trace_options.read_fn: hardening: and
** batched: suites.)
*/
#include "test.h"
#include "util.h"

#include <errno.h>
#include <stdio.h>
#include <string.h>
#include <unistd.h>

#define MAX_READS 10000   /* far more reads than any operation here makes */

/* A plain soup and an instanced scene, as scene sources. */
static void plain_source(tu_scene *soup, brt_mesh *mesh)
{
    uint64_t st = test_seed();
    tu_random_soup(soup, &st, 3000, 0.05f);
    *mesh = tu_mesh_view(soup);
}

/* Opens path with a fault at every read in turn; returns the faults met. */
static int open_with_faults(const char *path, const char *name)
{
    int faults = 0;
    long n;
    for (n = 0; n < MAX_READS; n++) {
        brt_scene *scene = NULL;
        brt_error err;
        brt_result r;
        err.message[0] = 0;
        brt_test_read_fault(n, EIO);
        r = brt_scene_open(path, &scene, &err);
        brt_test_read_fault(-1, 0);
        if (r == BRT_OK) {
            brt_scene_close(scene);
            break;
        }
        faults++;
        EXPECT(r == BRT_EIO && strstr(err.message, name) && strstr(err.message, "Input/output error"),
               "open, fault at read %ld: %s, '%s'", n, brt_result_string(r), err.message);
        if (test_failed()) break;
    }
    return faults;
}

static void test_open(void)
{
    tu_scene soup = {0};
    tu_instanced inst;
    brt_scene_source source;
    brt_scene_options opt;
    brt_mesh mesh;
    brt_error err;
    const char *plain = tu_scratch("faults-open.brs");
    int faults;
    plain_source(&soup, &mesh);
    memset(&opt, 0, sizeof opt);
    opt.batch_tris = 100;
    opt.proxy_res = 16;
    CHECK(brt_scene_build(&mesh, &opt, 1, plain, &err) == BRT_OK, "%s", err.message);
    faults = open_with_faults(plain, "faults-open.brs");
    EXPECT(faults >= 4, "a plain scene's open met only %d faults", faults);
    memset(&inst, 0, sizeof inst);
    tu_instanced_squares(&inst);
    tu_instanced_source(&inst, &source);
    plain = tu_scratch("faults-open4.brs");
    CHECK(brt_scene_build_source(&source, &opt, 1, plain, &err) == BRT_OK, "%s", err.message);
    faults = open_with_faults(plain, "faults-open4.brs");
    EXPECT(faults >= 5, "an instanced scene's open met only %d faults", faults);
    tu_instanced_free(&inst);
    tu_scene_free(&soup);
}

/* Builds with a fault at every read in turn (the spill file, and an
** instanced build's instance file): each fails cleanly. */
static int build_with_faults(const brt_mesh *mesh, const brt_scene_source *source, const char *path)
{
    brt_scene_options opt;
    int faults = 0;
    long n;
    memset(&opt, 0, sizeof opt);
    opt.batch_tris = 100;
    opt.proxy_res = 16;
    opt.threads = 1;
    for (n = 0; n < MAX_READS; n++) {
        brt_error err;
        brt_result r;
        err.message[0] = 0;
        unlink(path);
        brt_test_read_fault(n, EIO);
        r = mesh ? brt_scene_build(mesh, &opt, 1, path, &err) : brt_scene_build_source(source, &opt, 1, path, &err);
        brt_test_read_fault(-1, 0);
        if (r == BRT_OK) break;
        faults++;
        EXPECT(r == BRT_EIO && strstr(err.message, path) && strstr(err.message, "Input/output error"),
               "build, fault at read %ld: %s, '%s'", n, brt_result_string(r), err.message);
        EXPECT(!tu_file_exists(path) && !tu_temporary_file_left(), "build, fault at read %ld: a file left", n);
        if (test_failed()) break;
    }
    return faults;
}

static void test_build(void)
{
    tu_scene soup = {0};
    tu_instanced inst;
    brt_scene_source source;
    brt_mesh mesh;
    int faults;
    plain_source(&soup, &mesh);
    faults = build_with_faults(&mesh, NULL, tu_scratch("faults-build.brs"));
    EXPECT(faults >= 1, "a plain build met no fault (its spill file is read back)");
    memset(&inst, 0, sizeof inst);
    tu_instanced_squares(&inst);
    tu_instanced_source(&inst, &source);
    faults = build_with_faults(NULL, &source, tu_scratch("faults-build4.brs"));
    EXPECT(faults >= 2, "an instanced build met only %d faults", faults);
    tu_instanced_free(&inst);
    tu_scene_free(&soup);
}

void suite_faults(void)
{
    test_run("faults: a read fault at every read of a scene file's open", test_open);
    test_run("faults: a read fault at every read of a build (spill, instances)", test_build);
}
