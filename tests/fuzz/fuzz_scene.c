/* tests/fuzz/fuzz_scene.c -- libFuzzer entry point: the scene-file
** reader, brt_scene_open and a short brt_scene_trace (targets.c). */
#include "targets.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    return fuzz_entry("scene", data, size);
}
