// Named data across the native boundary: C++ structs filled from Python keyword arguments, field by field.
//
// Each Python object the kernel renders exports its own `native_data()` (a dict of field names); the kernel module
// builds the struct with `_native.Method(**method.native_data())`. A field that one side names and the other does
// not fails at once with a message naming it: an unknown keyword ("Method has no field 'stagse' (its fields: ...)"),
// a required field not given ("Method is missing the field 'stages'"), a value of the wrong type ("Method.stages:
// expected int, got str"). Each such class lists its field names in its `fields` attribute.
#pragma once

#include <functional>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include <nanobind/nanobind.h>

namespace multibody_sim
{
  namespace nb = nanobind;

  // The fields of struct T by name: how to set each from a Python value, and whether it must be given.
  template<typename T>
  class Fields
  {
  public:
    using Setter = std::function<void(T &, nb::handle)>;

    explicit Fields(std::string type)
    : type_(std::move(type))
    {
    }

    // A field set by `set` (which raises naming the field when the value does not fit).
    Fields & custom(const char * name, Setter set, bool required = true)
    {
      names_.emplace_back(name);
      required_.push_back(required);
      setters_.push_back(std::move(set));
      return *this;
    }

    // A member of type M, cast from the value; `expected` names the Python type in messages.
    template<typename M>
    Fields & member(const char * name, M T::*field, const char * expected, bool required = true)
    {
      const std::string where = type_ + "." + name;
      return custom(
        name, [field, where, expected](T & self, nb::handle value) { cast_into(self.*field, value, where, expected); },
        required);
    }

    // An enum member given by name (one of `names`).
    template<typename E>
    Fields & choice(const char * name, E T::*field, std::vector<std::pair<std::string, E>> names)
    {
      const std::string where = type_ + "." + name;
      return custom(name, [field, where, names](T & self, nb::handle value) {
        std::string text;
        cast_into(text, value, where, "str");
        std::string options;
        for (const auto & [candidate, parsed] : names)
        {
          if (candidate == text)
          {
            self.*field = parsed;
            return;
          }
          options += (options.empty() ? "'" : ", '") + candidate + "'";
        }
        throw nb::value_error((where + " must be one of " + options + ", got '" + text + "'").c_str());
      });
    }

    // A T from keyword arguments: every key must be a field, every required field given.
    T parse(const nb::kwargs & kwargs) const
    {
      T out{};
      std::vector<bool> given(names_.size(), false);
      for (auto [key, value] : kwargs)
      {
        const std::string name = nb::cast<std::string>(key);
        size_t i = 0;
        while (i < names_.size() && names_[i] != name)
          ++i;
        if (i == names_.size())
          throw nb::type_error((type_ + " has no field '" + name + "' (its fields: " + listing() + ")").c_str());
        setters_[i](out, value);
        given[i] = true;
      }
      for (size_t i = 0; i < names_.size(); ++i)
        if (required_[i] && !given[i])
          throw nb::type_error((type_ + " is missing the field '" + names_[i] + "'").c_str());
      return out;
    }

    // nb::cast<M>(value) into `field`, or a TypeError naming `where` and the value's type.
    template<typename M>
    static void cast_into(M & field, nb::handle value, const std::string & where, const char * expected)
    {
      try
      {
        field = nb::cast<M>(value);
      }
      catch (const nb::cast_error &)
      {
        const std::string got = nb::cast<std::string>(value.type().attr("__name__"));
        throw nb::type_error((where + ": expected " + expected + ", got " + got).c_str());
      }
    }

    const std::string & type() const
    {
      return type_;
    }

    nb::tuple names() const
    {
      nb::list out;
      for (const std::string & name : names_)
        out.append(nb::str(name.c_str()));
      return nb::tuple(out);
    }

  private:
    std::string listing() const
    {
      std::string out;
      for (size_t i = 0; i < names_.size(); ++i)
        out += (i ? ", " : "") + names_[i];
      return out;
    }

    std::string type_;
    std::vector<std::string> names_;
    std::vector<bool> required_;
    std::vector<Setter> setters_;
  };

  // Binds a plain struct T as class `name`: its fields readable and writable by name, constructed from keywords only
  // (`check` runs on the parsed struct, for shapes and ranges, before it is kept).
  template<typename T>
  class Struct
  {
  public:
    Struct(nb::module_ & m, const char * name, const char * doc)
    : cls_(m, name, doc)
    , fields_(std::make_shared<Fields<T>>(name))
    {
    }

    template<typename M>
    Struct & field(const char * name, M T::*member, const char * expected, bool required = true)
    {
      cls_.def_rw(name, member);
      fields_->member(name, member, expected, required);
      return *this;
    }

    template<typename M>
    Struct & optional(const char * name, M T::*member, const char * expected)
    {
      return field(name, member, expected, false);
    }

    // A field that may be None, which leaves the member as T{} has it.
    template<typename M>
    Struct & nullable(const char * name, M T::*member, const char * expected)
    {
      cls_.def_rw(name, member);
      const std::string where = std::string(fields_->type()) + "." + name;
      fields_->custom(name, [member, where, expected](T & self, nb::handle value) {
        if (!value.is_none())
          Fields<T>::cast_into(self.*member, value, where, expected);
      });
      return *this;
    }

    template<typename E>
    Struct & choice(const char * name, E T::*member, std::vector<std::pair<std::string, E>> names)
    {
      cls_.def_prop_ro(name, [member, names](const T & self) {
        for (const auto & [text, value] : names)
          if (value == self.*member)
            return text;
        return std::string("?");
      });
      fields_->choice(name, member, std::move(names));
      return *this;
    }

    nb::class_<T> & finish(std::function<void(T &)> check = nullptr)
    {
      std::shared_ptr<const Fields<T>> fields = fields_;
      cls_.def("__init__", [fields, check](T * self, nb::kwargs kwargs) {
        T parsed = fields->parse(kwargs);
        if (check)
          check(parsed);
        new (self) T(std::move(parsed));
      });
      cls_.attr("fields") = fields_->names();
      return cls_;
    }

  private:
    nb::class_<T> cls_;
    std::shared_ptr<Fields<T>> fields_;
  };
} // namespace multibody_sim
