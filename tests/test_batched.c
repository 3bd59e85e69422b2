#include "test.h"
void suite_batched(void) {}
