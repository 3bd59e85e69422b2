/* examples/common.c -- placeholder */
#include "common.h"
