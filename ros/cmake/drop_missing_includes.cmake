# ROS 2 wheels from PyPI (x86_64 laptops and CI) export the include directories of the
# machine that built them (/opt/python/...). CMake refuses imported targets that name a
# missing directory, so every interface package of this repository calls this after its
# last find_package (service_msgs comes with the srv files): it drops those entries, and
# relative ones. The generated code gets this machine's Python and NumPy include directories
# from rosidl itself. On an apt install every path exists and this changes nothing.
function(rovercan_drop_missing_includes)
  get_property(_imported DIRECTORY PROPERTY IMPORTED_TARGETS)
  foreach(_target IN LISTS _imported)
    get_target_property(_dirs ${_target} INTERFACE_INCLUDE_DIRECTORIES)
    if(_dirs)
      list(FILTER _dirs INCLUDE REGEX "^\\$<|^/")
      set(_existing "")
      foreach(_dir IN LISTS _dirs)
        if(EXISTS "${_dir}" OR _dir MATCHES "^\\$<")
          list(APPEND _existing "${_dir}")
        endif()
      endforeach()
      set_target_properties(${_target} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_existing}")
    endif()
  endforeach()
endfunction()
