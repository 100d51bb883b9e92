# The ROS 2 Jazzy wheels on PyPI export their *__rosidl_generator_py targets with
# the include dirs of the machine that built them (/opt/python/cp311-cp311/...).
# Point them at this interpreter's Python and NumPy headers instead. On a regular
# ROS install the paths exist and this is a no-op in effect.
find_package(Python3 REQUIRED COMPONENTS Interpreter Development.Module NumPy)
foreach(dep std_msgs geometry_msgs builtin_interfaces service_msgs)
  set(_tgt ${dep}::${dep}__rosidl_generator_py)
  if(TARGET ${_tgt})
    get_target_property(_inc ${_tgt} INTERFACE_INCLUDE_DIRECTORIES)
    if(_inc MATCHES "/opt/python/")
      set_target_properties(${_tgt} PROPERTIES
        INTERFACE_INCLUDE_DIRECTORIES "${Python3_INCLUDE_DIRS};${Python3_NumPy_INCLUDE_DIRS}")
    endif()
  endif()
endforeach()
