/* tests/fuzz/fuzz_rays.c -- libFuzzer entry point: the ray-file
** reader, brt_rays_read, and the rays traced exactly (targets.c). */
#include "targets.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    return fuzz_entry("rays", data, size);
}
