/* tests/test_embree.c -- placeholder until its issue lands. */
#include "test.h"
void suite_embree(void) {}
