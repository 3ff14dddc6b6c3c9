// Backward-pass kernels of the trainer. Internal to trainer/.
#pragma once

#include <cstddef>

namespace lsnif::trainer::detail {

// dWt[i][o] += sum_r X[r*ldx + i] * G[r*outp + o] for i < in, o < outp (outp multiple
// of 16). The weight-gradient GEMM (X^T G) in the layout the forward kernel reads.
void outer_accumulate(const float* X, std::size_t n, std::size_t in, std::size_t ldx, const float* G,
                      std::size_t outp, float* dWt);

}  // namespace lsnif::trainer::detail
