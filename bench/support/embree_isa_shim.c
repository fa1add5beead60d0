/* Caps the instruction set of an Embree the bench cannot configure (the one Mitsuba 3 bundles)
 * at EMBREE_MAX_ISA (default avx2): loaded with LD_PRELOAD, this rtcNewDevice appends
 * max_isa=EMBREE_MAX_ISA to the configuration the program asked for and calls Embree's own.
 * bench/worker_throughput.py compiles it into a temporary directory for its AVX2 comparison
 * (--isa avx2); the worker caps its own Embree through RENDERFARM_ISA. */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>

typedef void *(*NewDevice)(const char *);

void *rtcNewDevice(const char *config) {
  NewDevice real = (NewDevice)dlsym(RTLD_NEXT, "rtcNewDevice");
  /* An Embree loaded as a dependency of a Python extension sits in that extension's local
   * scope, which RTLD_NEXT does not search: look it up by its name once it is loaded. */
  const char *names[] = {"libembree3.so", "libembree3.so.3"};
  for (int i = 0; !real && i < 2; ++i) {
    void *lib = dlopen(names[i], RTLD_NOW | RTLD_NOLOAD);
    if (lib) real = (NewDevice)dlsym(lib, "rtcNewDevice");
  }
  if (!real) {
    fprintf(stderr, "embree_isa_shim: Embree's rtcNewDevice not found\n");
    abort();
  }
  const char *isa = getenv("EMBREE_MAX_ISA");
  char capped[1024];
  snprintf(capped, sizeof capped, "%s%smax_isa=%s", config ? config : "",
           config && *config ? "," : "", isa && *isa ? isa : "avx2");
  fprintf(stderr, "embree_isa_shim: rtcNewDevice(\"%s\")\n", capped);
  return real(capped);
}
