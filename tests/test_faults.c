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

/* One operation under test: it reads through the library's own reader. */
typedef struct operation {
    const char *path;                   /* the file it opens or builds */
    const brt_mesh *mesh;               /* a build: of this mesh, or */
    const brt_scene_source *source;     /* of this source; neither: an open */
} operation;

static brt_result run_operation(const operation *op, brt_error *err)
{
    brt_scene_options opt;
    brt_scene *scene = NULL;
    brt_result r;
    memset(&opt, 0, sizeof opt);
    opt.point_tris = 100;
    opt.proxy_res = 16;
    opt.threads = 1;                    /* one countdown: no reader beside it */
    if (!op->mesh && !op->source) {
        r = brt_scene_open(op->path, &scene, err);
        if (r == BRT_OK) brt_scene_close(scene);
        return r;
    }
    unlink(op->path);
    return op->mesh ? brt_scene_build(op->mesh, &opt, 1, op->path, err)
                    : brt_scene_build_source(op->source, &opt, 1, op->path, err);
}

/* Runs op with a fault at its n-th read for n = 0, 1, ... until it needs
** no more reads; each fault must end it with BRT_EIO naming the file (a
** build leaving no file); returns the faults met. */
static int fault_every_read(const operation *op)
{
    const char *name = strrchr(op->path, '/') ? strrchr(op->path, '/') + 1 : op->path;
    int faults = 0;
    long n;
    for (n = 0; n < MAX_READS; n++) {
        brt_error err;
        brt_result r;
        err.message[0] = 0;
        brt_test_read_fault(n, EIO);
        r = run_operation(op, &err);
        brt_test_read_fault(-1, 0);
        if (r == BRT_OK) break;
        faults++;
        EXPECT(r == BRT_EIO && strstr(err.message, name) && strstr(err.message, "Input/output error"),
               "%s, fault at read %ld: %s, '%s'", name, n, brt_result_string(r), err.message);
        if (op->mesh || op->source)
            EXPECT(!tu_file_exists(op->path) && !tu_temporary_file_left(), "%s, fault at read %ld: a file left",
                   name, n);
        if (test_failed()) break;
    }
    return faults;
}

static void test_open(void)
{
    tu_scene soup = {0};
    tu_instanced inst;
    brt_scene_source source;
    brt_mesh mesh;
    operation build = {NULL, NULL, NULL}, open = {NULL, NULL, NULL};
    brt_error err;
    plain_source(&soup, &mesh);
    memset(&inst, 0, sizeof inst);
    tu_instanced_squares(&inst);
    tu_instanced_source(&inst, &source);
    build.path = open.path = tu_scratch("faults-open.brs");
    build.mesh = &mesh;
    CHECK(run_operation(&build, &err) == BRT_OK, "%s", err.message);
    EXPECT(fault_every_read(&open) >= 4, "a plain scene's open met fewer faults than its 4 reads");
    build.path = open.path = tu_scratch("faults-open4.brs");
    build.mesh = NULL;
    build.source = &source;
    CHECK(run_operation(&build, &err) == BRT_OK, "%s", err.message);
    EXPECT(fault_every_read(&open) >= 5, "an instanced scene's open met fewer faults than its 5 reads");
    tu_instanced_free(&inst);
    tu_scene_free(&soup);
}

/* Builds: the spill file, and an instanced build's instance file. */
static void test_build(void)
{
    tu_scene soup = {0};
    tu_instanced inst;
    brt_scene_source source;
    brt_mesh mesh;
    operation op = {NULL, NULL, NULL};
    plain_source(&soup, &mesh);
    op.path = tu_scratch("faults-build.brs");
    op.mesh = &mesh;
    EXPECT(fault_every_read(&op) >= 1, "a plain build met no fault (its spill file is read back)");
    memset(&inst, 0, sizeof inst);
    tu_instanced_squares(&inst);
    tu_instanced_source(&inst, &source);
    op.path = tu_scratch("faults-build4.brs");
    op.mesh = NULL;
    op.source = &source;
    EXPECT(fault_every_read(&op) >= 2, "an instanced build met fewer than 2 faults");
    tu_instanced_free(&inst);
    tu_scene_free(&soup);
}

void suite_faults(void)
{
    test_run("faults: a read fault at every read of a scene file's open", test_open);
    test_run("faults: a read fault at every read of a build (spill, instances)", test_build);
}
