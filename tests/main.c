/*
** tests/main.c -- the test runner: runs every suite, prints one line per
** failed or skipped test, and ends with exactly "N passed, N failed".
**
** Usage: build/run_tests [NAME-SUBSTRING...]   (no argument: all tests)
** Environment: BRT_TEST_SEED=S replays random tests; BRT_SHARED=DIR points
** at the shared data (default ../shared, relative to the repository).
*/
#include "test.h"

#include <stdarg.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

static int passed, failed, skipped;
static int current_failed, current_skipped;
static const char *current_name = "";
static char **filters;
static int filter_count;
static char tmpdir[256];

static int selected(const char *name)
{
    int i;
    if (filter_count == 0) return 1;
    for (i = 0; i < filter_count; i++)
        if (strstr(name, filters[i])) return 1;
    return 0;
}

void test_run(const char *name, test_fn fn)
{
    if (!selected(name)) return;
    current_name = name;
    current_failed = current_skipped = 0;
    fn();
    if (current_failed) failed++;
    else if (current_skipped) skipped++;
    else passed++;
    fflush(stdout);
}

void test_fail_at(const char *file, int line, const char *fmt, ...)
{
    va_list ap;
    printf("FAIL %s: %s:%d: ", current_name, file, line);
    va_start(ap, fmt);
    vprintf(fmt, ap);
    va_end(ap);
    printf(" (seed %llu)\n", (unsigned long long)test_seed());
    current_failed = 1;
}

void test_skip(const char *fmt, ...)
{
    va_list ap;
    printf("SKIP %s: ", current_name);
    va_start(ap, fmt);
    vprintf(fmt, ap);
    va_end(ap);
    printf("\n");
    current_skipped = 1;
}

int test_failed(void) { return current_failed; }

uint64_t test_seed(void)
{
    const char *s = getenv("BRT_TEST_SEED");
    return s ? strtoull(s, NULL, 10) : 20200525u;
}

const char *test_tmpdir(void)
{
    if (!tmpdir[0]) {
        snprintf(tmpdir, sizeof tmpdir, "/tmp/batchrt-test-%ld", (long)getpid());
        mkdir(tmpdir, 0700);
    }
    return tmpdir;
}

const char *test_shared_mesh(const char *name)
{
    static char paths[16][512];
    static int next;
    char src[512], cmd[4 * 512 + 64];   /* src and three uses of out, each < 512 */
    const char *shared = getenv("BRT_SHARED");
    char *out = paths[next++ % 16];
    size_t len = strlen(name);
    struct stat st;

    snprintf(src, sizeof src, "%s/data/meshes/%s", shared ? shared : "../shared", name);
    if (stat(src, &st) != 0) return NULL;
    if (len < 3 || strcmp(name + len - 3, ".gz") != 0) {
        snprintf(out, 512, "%s", src);
        return out;
    }
    /* Unpack once per run with the system's gzip: the library reads no gzip. */
    snprintf(out, 512, "%s/%.*s", test_tmpdir(), (int)(len - 3), name);
    if (stat(out, &st) == 0) return out;
    snprintf(cmd, sizeof cmd, "gzip -dc '%s' > '%s.part' && mv '%s.part' '%s'", src, out, out, out);
    if (system(cmd) != 0) return NULL;
    return out;
}

static void remove_tmpdir(void)
{
    char cmd[300];
    if (!tmpdir[0]) return;
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", tmpdir);
    if (system(cmd) != 0) fprintf(stderr, "could not remove %s\n", tmpdir);
}

int main(int argc, char **argv)
{
    filters = argv + 1;
    filter_count = argc - 1;
    setvbuf(stdout, NULL, _IOLBF, 0);
    suite_mesh();
    suite_bvh();
    suite_svdag();
    suite_batched();
    suite_cli();
    suite_scenes();
    suite_render();
    suite_referee();
    suite_embree();
    suite_hardening();
    suite_build();
    suite_occlusion();
    suite_threads();
    suite_inner();
    suite_follow();
    suite_layers();
    suite_sampling();
    suite_reclaim();
    if (failed == 0) remove_tmpdir();
    else if (tmpdir[0]) printf("scratch files kept in %s\n", tmpdir);
    if (skipped) printf("(%d skipped, see SKIP lines above)\n", skipped);
    printf("%d passed, %d failed\n", passed, failed);
    return failed ? 1 : 0;
}
