/* svdag.c -- placeholder */
#include "batchrt.h"
