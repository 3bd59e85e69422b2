/*
** tests/test.h -- batchrt's own tiny test runner (no framework).
**
** A test is a function void f(void).  CHECK records a failure with file,
** line and a printf message, and returns from the test; helpers that are
** not tests use EXPECT (records, does not return) and test_failed().
** Each suite file defines one function suite_NAME() that calls
** test_run() for its tests; tests/main.c calls every suite.  The runner
** prints one line per failure or skip and ends with "N passed, N failed".
**
** Random tests take their seed from test_seed() and print it on failure,
** so any failure can be replayed with BRT_TEST_SEED=<seed>.
*/
#ifndef BRT_TEST_H
#define BRT_TEST_H

#include <stdint.h>
#include <stdio.h>

typedef void (*test_fn)(void);

/* Runs one test unless a name filter given on the command line excludes it. */
void test_run(const char *name, test_fn fn);

/* Records a failure of the running test (printf message). */
void test_fail_at(const char *file, int line, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 3, 4)))
#endif
    ;

/* Marks the running test skipped, visibly, with a reason. */
void test_skip(const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 1, 2)))
#endif
    ;

/* Is a test of this exact name in the suite (filters aside)?  While it
** collects the names, test_listing() is 1: a suite that registers some
** tests only where an optional program exists registers them all then. */
int test_registered(const char *name);
int test_listing(void);

int test_failed(void);          /* has the running test failed so far? */
uint64_t test_seed(void);       /* BRT_TEST_SEED or a fixed default */

/* A fresh scratch directory for this run (removed at exit when all pass). */
const char *test_tmpdir(void);

/* Path of a shared mesh (../shared/data/meshes/NAME), gunzipped into the
** scratch directory when NAME ends in .gz; NULL when ../shared is absent
** (the caller then calls test_skip). Set BRT_SHARED to point elsewhere. */
const char *test_shared_mesh(const char *name);

#define EXPECT(cond, ...) \
    do { if (!(cond)) test_fail_at(__FILE__, __LINE__, __VA_ARGS__); } while (0)
#define CHECK(cond, ...) \
    do { if (!(cond)) { test_fail_at(__FILE__, __LINE__, __VA_ARGS__); return; } } while (0)

/* The suites (one per file in tests/). */
void suite_mesh(void);
void suite_bvh(void);
void suite_svdag(void);
void suite_batched(void);
void suite_exchange(void);
void suite_faults(void);
void suite_mpi(void);
void suite_cli(void);
void suite_scenes(void);
void suite_instanced_scenes(void);
void suite_render(void);
void suite_point_size(void);
void suite_referee(void);
void suite_embree(void);
void suite_hardening(void);
void suite_build(void);
void suite_occlusion(void);
void suite_threads(void);
void suite_inner(void);
void suite_entry(void);
void suite_follow(void);
void suite_instances(void);
void suite_layers(void);
void suite_sampling(void);
void suite_reclaim(void);
void suite_runner(void);
void suite_pbrt(void);
void suite_pbrt_camera(void);
void suite_pbrt_state(void);
void suite_loopsubdiv(void);
void suite_policy(void);
void suite_reference(void);
void suite_thresholds(void);
void suite_oom(void);
void suite_drift(void);

#endif
