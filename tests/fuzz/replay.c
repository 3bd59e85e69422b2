/*
** tests/fuzz/replay.c -- replays fuzz inputs without libFuzzer or clang:
** every file of each folder (or each file) given runs through one target
** of targets.h, so CI checks tests/corpus/ with the plain compiler.
**
**   build/tests/fuzz/replay TARGET DIR|FILE...   (TARGET: obj ply scene rays pbrt)
**
** Exit status 0 when every input keeps every property, 1 otherwise.
*/
#include "targets.h"

#include <stdio.h>

static void report(const char *file, const char *problem, void *user)
{
    long *problems = user;
    fprintf(stderr, "replay: %s: %s\n", file, problem);
    ++*problems;
}

int main(int argc, char **argv)
{
    const fuzz_target *target = argc > 2 ? fuzz_find(argv[1]) : NULL;
    long inputs = 0, problems = 0;
    int i;
    if (!target) {
        fprintf(stderr, "usage: replay obj|ply|scene|rays|pbrt DIR|FILE...\n");
        return 1;
    }
    for (i = 2; i < argc; i++) {
        long n = fuzz_replay(target, argv[i], report, &problems);
        if (n < 0) {
            fprintf(stderr, "replay: %s: cannot read\n", argv[i]);
            return 1;
        }
        inputs += n;
    }
    printf("replay %s: %ld inputs, %ld problems\n", target->name, inputs, problems);
    return problems ? 1 : 0;
}
