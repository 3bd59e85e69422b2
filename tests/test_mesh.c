#include "test.h"
void suite_mesh(void) {}
