// PALPSIM_HD marks per-voxel math that both backends compile: empty for the host
// compiler, __host__ __device__ under nvcc (Open3D's *Impl.h pattern).
#pragma once

#if defined(__CUDACC__)
#define PALPSIM_HD __host__ __device__ __forceinline__
#else
#define PALPSIM_HD inline
#endif
