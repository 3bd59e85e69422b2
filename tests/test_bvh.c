#include "test.h"
void suite_bvh(void) {}
