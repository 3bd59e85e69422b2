/* tests/test_hardening.c -- placeholder until its issue lands. */
#include "test.h"
void suite_hardening(void) {}
