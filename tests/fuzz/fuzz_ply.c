/* tests/fuzz/fuzz_ply.c -- libFuzzer entry point: the PLY reader,
** brt_mesh_parse_ply (checks in targets.c). */
#include "targets.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    return fuzz_entry("ply", data, size);
}
