#include "test.h"
void suite_svdag(void) {}
