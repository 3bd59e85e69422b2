/*
** examples/bench/bench_pbrt.c -- reading speed of the pbrt-v4 reader
** (examples/lib/pbrt.c) against the OBJ reader (mesh.c) on the same
** triangles, as a program pays it: the input opened (ex_input_open: for a
** .pbrt file, pass 1 over the whole file) and every triangle streamed once
** through the scene source, as a build's pass does.  Prints a Markdown
** table, never pass/fail ("make bench-pbrt").
**
** Usage: build/bench_pbrt MESH.obj SCENE.pbrt [--repeat N]
**   SCENE.pbrt holds the same triangles as MESH.obj (world shapes, same
**   order, same number text); the streamed corners are compared bit for
**   bit and a difference is an error.  Each reader runs N times (default
**   5), alternating, wall-clock seconds (the files stay in the page cache
**   after the first run: the figures are the parsers', not the disk's).
*/
#include "batchrt.h"
#include "common.h"
#include "input.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *prog = "bench_pbrt";

/* What a run streamed: the count and an FNV-1a hash of the corners' bits. */
typedef struct tally { uint64_t triangles, hash; } tally;

static brt_result count_triangles(void *user, const float *corners, uint32_t count, uint32_t first,
                                  brt_error *err)
{
    tally *t = user;
    size_t i;
    (void)first;
    (void)err;
    for (i = 0; i < 9 * (size_t)count; i++) {
        uint32_t bits;
        memcpy(&bits, &corners[i], sizeof bits);
        t->hash = (t->hash ^ bits) * 1099511628211ull;
    }
    t->triangles += count;
    return BRT_OK;
}

/* One open and stream of path; returns the seconds. */
static double read_once(const char *path, tally *t)
{
    ex_input in;
    brt_error err;
    double start = brt_seconds();
    memset(t, 0, sizeof *t);
    t->hash = 14695981039346656037ull;
    ex_input_open(prog, path, &in);
    if (in.source.prototype_count > 0) ex_die(prog, "%s: has instances; the bench wants world shapes only", path);
    ex_check(prog, in.source.world.run(in.source.world.user, count_triangles, t, &err), &err);
    ex_input_close(&in);
    return brt_seconds() - start;
}

int main(int argc, char **argv)
{
    const char *paths[2];
    double best[2] = {1e300, 1e300}, worst[2] = {0, 0};
    tally t[2];
    long repeat = 5, i;
    int k;
    if (ex_wants_help(argc, argv)) {
        printf("usage: bench_pbrt MESH.obj SCENE.pbrt [--repeat N]\n"
               "  opens and streams the same triangles as an OBJ and as a pbrt file, N times each\n"
               "  (default 5), checks that both stream the same bits, and prints the seconds\n");
        return 0;
    }
    if (argc != 3 && !(argc == 5 && strcmp(argv[3], "--repeat") == 0 && (repeat = atol(argv[4])) > 0))
        ex_die(prog, "usage: bench_pbrt MESH.obj SCENE.pbrt [--repeat N]");
    paths[0] = argv[1];
    paths[1] = argv[2];
    for (i = 0; i < repeat; i++)
        for (k = 0; k < 2; k++) {
            double s = read_once(paths[k], &t[k]);
            if (s < best[k]) best[k] = s;
            if (s > worst[k]) worst[k] = s;
        }
    if (t[0].triangles != t[1].triangles || t[0].hash != t[1].hash)
        ex_die(prog, "%s and %s stream different triangles (%llu and %llu)", paths[0], paths[1],
               (unsigned long long)t[0].triangles, (unsigned long long)t[1].triangles);
    printf("%llu triangles, open + stream, wall-clock seconds, best and worst of %ld runs\n\n",
           (unsigned long long)t[0].triangles, repeat);
    printf("| reader | best s | worst s | M triangles/s, best | M triangles/s, worst |\n|---|---:|---:|---:|---:|\n");
    for (k = 0; k < 2; k++)
        printf("| %s | %.3f | %.3f | %.2f | %.2f |\n", k ? "pbrt trianglemesh" : "OBJ", best[k], worst[k],
               (double)t[k].triangles / best[k] * 1e-6, (double)t[k].triangles / worst[k] * 1e-6);
    printf("\npbrt / OBJ (best): %.2f\n", best[1] / best[0]);
    return 0;
}
