/* tests/fuzz/fuzz_pbrt.c -- libFuzzer entry point: the pbrt-v4 reader of
** examples/lib/pbrt.c, ex_pbrt_open and its streams (checks in targets.c). */
#include "targets.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    return fuzz_entry("pbrt", data, size);
}
