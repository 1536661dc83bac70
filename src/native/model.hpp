// A Pinocchio model handed over from Python, with the Data its algorithms work in (shared by the extension's
// translation units).
#pragma once

#include <cstddef>
#include <string>

#include <pinocchio/multibody.hpp>

namespace multibody_sim
{
  /// pinocchio::Model rebuilt from the bytes of Python's `model.saveToBinary(pin.serialization.StreamBuffer())`
  /// (a Boost binary archive: the same Boost, 1.90, reads it here), and one Data reused by every call.
  struct NativeModel
  {
    pinocchio::Model model;
    pinocchio::Data data;

    /// Throws std::invalid_argument naming the problem if the bytes are not such an archive.
    NativeModel(const char * bytes, std::size_t size);
  };
} // namespace multibody_sim
