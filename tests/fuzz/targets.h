/*
** tests/fuzz/targets.h -- the five fuzz targets of batchrt: the OBJ reader,
** the PLY reader, the scene-file reader, the ray-file reader (README,
** "Tests") and the pbrt-v4 reader of examples/lib/pbrt.c.
**
** One implementation (targets.c) serves three drivers: the libFuzzer entry
** points tests/fuzz/fuzz_NAME.c ("make fuzz", clang), the plain replay
** driver tests/fuzz/replay.c ("make fuzz-replay", any C99 compiler), and
** the test suite (tests/test_hardening.c replays tests/corpus/NAME/).
** A target feeds one input to a reader and checks what must hold whatever
** the bytes (in the spirit of cgltf's fuzz harness): a result code from
** the documented set, a one-line message naming the input on failure, a
** zeroed mesh on error, valid indices and finite coordinates on success,
** and hits equal to an exact oracle.  Crashes, leaks and undefined
** behaviour are the sanitizers' to find.
*/
#ifndef BRT_FUZZ_TARGETS_H
#define BRT_FUZZ_TARGETS_H

#include "batchrt.h"
#include "testing.h"

#include <stddef.h>
#include <stdint.h>

/* Runs one input; NULL when every property held, else a static text
** naming the first one violated. */
typedef const char *(*fuzz_fn)(const uint8_t *data, size_t size);

typedef struct fuzz_target {
    const char *name;   /* "obj", "ply", "scene", "rays", "pbrt": also the corpus folder */
    fuzz_fn run;
} fuzz_target;

/* The targets, ended by {NULL, NULL}. */
extern const fuzz_target fuzz_targets[];

/* The target of that name, or NULL. */
const fuzz_target *fuzz_find(const char *name);

/* Runs every regular file of dir (or the file dir itself) through target,
** calling report(file, problem, user) for each violation.  Returns the
** number of inputs run, or -1 when dir cannot be read. */
long fuzz_replay(const fuzz_target *target, const char *dir,
                 void (*report)(const char *file, const char *problem, void *user),
                 void *user);

/* The fixed mesh behind the "rays" target (a few dozen triangles in
** [-1,1]^3 with a duplicate and a degenerate one) and its scene file, as
** the "scene" target's seed in tests/corpus/scene/ was made. */
void fuzz_fixed_mesh(brt_mesh *mesh);   /* static arrays: do not free */
brt_result fuzz_fixed_scene_build(const char *path, brt_error *err);
/* Recomputes every checksum of a (damaged) scene file, as a forger would. */
void fuzz_repair_scene_checksums(uint8_t *file, size_t size);

/* libFuzzer: runs the target of that name and abort()s, after printing
** the violated property, when it returns one. */
int fuzz_entry(const char *name, const uint8_t *data, size_t size);
int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

#endif
