/* tests/fuzz/fuzz_obj.c -- libFuzzer entry point: the OBJ reader,
** brt_mesh_parse_obj (checks in targets.c). */
#include "targets.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    return fuzz_entry("obj", data, size);
}
